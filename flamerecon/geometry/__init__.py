"""Where things are: cameras (kornia, OpenCV frame), the voxel grid, silhouettes, the visual
hull, and each camera's photometric response."""
