"""Built-in plant definitions (installed as ``prsa_ctrl.plants``)."""
