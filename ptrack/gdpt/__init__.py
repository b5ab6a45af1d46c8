"""General Defocusing Particle Tracking: calibration stacks as recorded (beads found, cropped, averaged,
interpolated between pages) and fast matching of large templates. :mod:`ptrack.calibration` is the public face."""
