"""The stages of ``turntable reconstruct``, one module each, in the order they run.

================  ==============================================================
``frames``        decode the input once: rings at full size, pixels at the work size
``cameras``       sequence calibration (``calibration``), ``--cameras``, or the cached one
``silhouettes``   automatic or ``--masks``; a verdict per view (ok / conservative / rejected)
``hull``          visual-hull carving in a working volume (``volume``) grown until the object fits
``fusion``        per-view stereo and the fused surface, kept only where held-out views confirm it
``texture``       the UV atlas and the photo texture of the final mesh (and ``--lods``), cached
``export``        the model files and exports (COLMAP, nerfstudio), into the staging folder
``summary``       the run's verdict (failed checks) and :class:`ReconstructSummary`: ``summary.json`` and the screen
================  ==============================================================

:mod:`turntable.reconstruct` runs them in order inside one :class:`turntable.outdir.OutputFolder`;
the work stages cache their results in :class:`turntable.stages.cache.StageCache`; the
Rerun recording is logged by :func:`turntable.recording.record_reconstruction`. ``options`` holds
:class:`ReconstructOptions`, which every stage reads; ``calibration`` is also what
``turntable calibrate-sequence`` runs.
"""
