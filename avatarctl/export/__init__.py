"""Taking the avatar out of the volume renderer: meshes (marching cubes of the density, baked colours), a skinned
glTF 2.0 avatar with the body's skeleton, its reload check, and a mesh rasteriser for scoring.

`mesh` (field -> coloured mesh), `skinning` (weights, pivots, joint TRS), `gltf` (the .glb writer), `gltf_read`
(read back and skin from the file's own data), `raster` (a mesh seen by a project camera).
"""
