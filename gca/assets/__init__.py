"""gca.assets: 3DGS ``.ply`` I/O (:mod:`.ply`), procedural textured objects and their static scans
(:mod:`.objects`, :mod:`.texture`, :mod:`.preview`), and Gaussians -> MPM particles with the
Gaussian-particle binding (:mod:`.particles`)."""
