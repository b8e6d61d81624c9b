"""The stages of the paper's Fig. 2, one module per stage, in data-flow order."""
