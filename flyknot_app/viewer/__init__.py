"""The 3D viewer and the pictures of trials."""
