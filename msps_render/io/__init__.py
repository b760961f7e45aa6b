"""File formats: EXR/PNG images (meshes are read by trimesh in scene.shapes)."""
