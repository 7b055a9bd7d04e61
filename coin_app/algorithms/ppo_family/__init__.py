"""The PPO-family baselines of the COIN paper on RLlib's new API stack: IPPO, CPPO and MFPO (CoPO: ``coin_app.algorithms.copo``)."""
