"""Image reconstruction: thermal-drift compensation, blind tip estimation, landmark extraction."""
