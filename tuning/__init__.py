"""Built-in tuning scenes (installed as ``prsa_ctrl.scenes``)."""
