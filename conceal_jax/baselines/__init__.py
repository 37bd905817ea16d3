"""Layer 5, beside robust: the ways to hide an image that the ConcealGS paper compares with (LSB and
DeepStega): the hidden image is put into the training views, a 3D-GS scene is trained on them, and the image
is read back from the render at the check view. Imports every layer below; robust and baselines do not
import each other."""
