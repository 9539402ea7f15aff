"""Data package ``proprio_models``: the MJCF elbow (``elbow.xml``), generated length fits and
the OpenSim ECRB curve of the wrist protocol (``wrist_ecrb.csv``).

No code lives here. In a wheel this folder is installed as the package ``proprio_models`` so
``importlib.resources`` finds the files; in a source checkout it is the top-level ``models/``.
Use ``proprio_env.body.model.model_path()`` and
``spindle.chain.length_model.default_fits_path()`` rather than building paths by hand.
"""
