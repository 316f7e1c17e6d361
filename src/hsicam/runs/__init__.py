"""Run folders: checkpoints (:mod:`~hsicam.runs.checkpoint`), layout, loading and the metrics log
(:mod:`~hsicam.runs.folder`), measured PSFs stored with a run (:mod:`~hsicam.runs.measured_psf`)."""
