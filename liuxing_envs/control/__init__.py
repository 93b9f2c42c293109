"""Robot controllers: how an action drives the arm, the gripper and the camera."""
