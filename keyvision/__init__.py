"""keyvision: keypoint estimators and renderers that learn cldyn dynamics from images."""
