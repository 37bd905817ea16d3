"""conceal_jax: hide and recover invisible copyright images in 3D Gaussian Splatting scenes (ConcealGS)."""
from conceal_jax.splat.camera import Camera
from conceal_jax.splat.gaussians import Gaussians
from conceal_jax.splat.render import RenderOptions, RenderOutput, render, render_batch

__all__ = ["Camera", "Gaussians", "RenderOptions", "RenderOutput", "render", "render_batch"]
