"""The safety layer: guards and monitors between a policy's commands and the robot."""
