"""The TD3 family's base (CIG-TD3, ITD3 and TraCo share it): the joint-step replay, its transitions and columns."""
