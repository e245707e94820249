"""Drive parameter-set templates (data files, see prsa_ctrl.io.driveparams)."""
