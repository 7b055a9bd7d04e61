"""Simulator backends behind the dict-of-agents env API: the native core and MetaDrive, picked by ``make_driving_env``."""
