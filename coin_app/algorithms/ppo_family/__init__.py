"""The PPO-family baselines of the COIN paper on RLlib's new API stack (IPPO so far; CPPO, MFPO, CoPO to come)."""
