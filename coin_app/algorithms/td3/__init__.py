"""The TD3 family's base: ITD3 (TD3 with parameter sharing), its replay, networks, losses and learner; CIG-TD3 and TraCo extend it."""
