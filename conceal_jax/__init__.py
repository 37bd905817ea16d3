"""conceal_jax: hide and recover invisible copyright images in 3D Gaussian Splatting scenes (ConcealGS)."""
from conceal_jax.camera import Camera
from conceal_jax.gaussians import Gaussians
from conceal_jax.render import RenderOptions, RenderOutput, render, render_batch

__all__ = ["Camera", "Gaussians", "RenderOptions", "RenderOutput", "render", "render_batch"]
