"""Drive parameter-set templates (data files, see prsa_ctrl.driveparams)."""
