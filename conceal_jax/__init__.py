"""conceal_jax: hide and recover invisible copyright images in 3D Gaussian Splatting scenes (ConcealGS)."""
from conceal_jax.core import lanes as _lanes

# Before any JAX backend starts: a CPU host becomes two XLA devices so that a step's independent halves
# can run on both cores (see core/lanes.py); single-device code is unaffected.
_lanes.split_host_cpu()

from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, RenderOutput, render, render_batch

__all__ = ["Camera", "Gaussians", "RenderOptions", "RenderOutput", "render", "render_batch"]
