"""The MuJoCo world shared by every environment: scene, arm, wrist depth camera, viewpoints."""
