"""Layer 5, beside robust: the ways to hide an image that the ConcealGS paper compares with: LSB and DeepStega
put the hidden image into the training views and train a 3D-GS scene on them; StegaNeRF trains the scene's
colour with a decoder so that renders carry it. The image is read back from the render at the check view.
Imports every layer below; robust and baselines do not import each other."""
