"""Layer 1: the differentiable splatting renderer (scene and camera pytrees, SH colour, EWA projection,
tile binning, compositing, `render`). Imports only `core`."""
