"""TraCo (Liu et al., CoRL 2023): the cross-attention domain critic and counterfactual baseline of COIN's TD3 baseline; networks so far."""
