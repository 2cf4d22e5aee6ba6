"""The forward model of the instrument (paper, "Forward Model"), from pupil to pixels.

- :mod:`~amigo.model.optics`: pupil, aperture mask and the propagation to the detector;
- :mod:`~amigo.model.bandpass`: the effective spectrum (filter x QE x star);
- :mod:`~amigo.model.visibility` and :mod:`~amigo.model.basis`: the latent visibility model;
- :mod:`~amigo.model.detector`: geometry, jitter, charge migration, ramps and read-out;
- :mod:`~amigo.model.image`: one level-2 exposure composed from the parts above;
- :mod:`~amigo.model.base`: the trained state of the whole instrument and its model file.

Nothing here knows about data likelihoods, solvers or workflows (those import this).
"""
