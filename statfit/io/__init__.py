"""Reading and writing files: meshes and point clouds, JSON-lines logs."""
