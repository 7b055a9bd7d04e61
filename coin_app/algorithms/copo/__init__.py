"""CoPO: coordinated policy optimization with local coordination factors (LCF) and an LCF meta-gradient (spec and config: ``copo.py``)."""
