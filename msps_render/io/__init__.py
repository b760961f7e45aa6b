"""Files in and out: images (`images.FORMATS`), 16-bit PNG (`png16`), all-or-nothing output
directories (`staging`); meshes are read by trimesh in scene.shapes."""
