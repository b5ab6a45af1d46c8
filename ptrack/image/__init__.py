"""The image half of the pipeline, one module per step.

``preprocess`` (invert, background, median) -> ``detect`` (noise and
background maps, false-alarm threshold, polarity, scale space) -> ``fit``
(maximum-likelihood Gaussian at the Cramer-Rao bound) or ``radial`` (radial
symmetry centres for rings and other non-blob images) -> ``locate`` (one
frame, the notebook entry point).
"""
