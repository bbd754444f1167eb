"""Asset export: UV baking (``uv_bake``) and GLB / OBJ writing (``gltf``)."""
