"""Surface normals of strips by plane fits over a grid."""
