"""The bot behind one interface (gantry, 2-DOF camera head, camera)."""
