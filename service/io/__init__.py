"""File formats: meshes (OBJ/PLY/NPZ), UV-space maps (EXR), marker files (JSON/CSV/TRC/C3D)."""
