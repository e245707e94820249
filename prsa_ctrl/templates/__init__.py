"""Drive parameter-set templates (data files, see prsa_ctrl.drive.params)."""
