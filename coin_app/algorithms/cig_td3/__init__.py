"""CIG-TD3 (COIN): counterfactual individual-global TD3 on RLlib's new API stack."""
