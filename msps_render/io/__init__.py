"""File formats: images (`images.FORMATS`); meshes are read by trimesh in scene.shapes."""
