"""hsicam's version, its one home: ``hsicam.__version__`` repeats it, the built wheel's metadata reads it
(pyproject's ``[tool.setuptools.dynamic]``), and the run records name it (:func:`hsicam.engine.provenance.running_version`).
A module of the lowest layer, so that any layer may read it without importing the package root."""

__version__ = "0.1.0"
