"""Layer 2: scenes on disk: dataset loaders (Blender, COLMAP, transforms.json), the generated demo scene,
and 3D-GS PLY files. Imports `splat` and `core`."""
