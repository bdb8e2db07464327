"""The sensors: everything that turns a world state into camera and LiDAR data.

Modules (data flows down):
    mesh.py         triangle meshes and their materials
    polyline.py     polylines on the ground and the triangles built along them
    furniture.py    signal heads, stop signs, buildings and trees beside the roads
    labelmap.py     the BEV label polygons kept beside the static mesh
    scene.py        the static scene of a town (mesh, label map), built once and cached
    actors.py       the road users' boxes as triangles
    embree.py       Embree 4 called from numba (the ray queries: the fast path)
    trimesh_rays.py the same queries through trimesh.ray (the portable path)
    raycast.py      the culled per-frame scene and ray batches on it; picks the ray backend
    lidar.py        the LiDAR sweep and its BEV counts
    shading.py      the camera's compiled per-pixel passes
    camera.py       the camera image
    config.py       SensorConfig: both sensors and the encoding
    overrides.py    `--sensor FIELD=VALUE` -> SensorConfig, values checked
"""
