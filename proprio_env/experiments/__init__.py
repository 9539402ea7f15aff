"""The experiments that reproduce the seed paper's figures ("Modelling muscle spindle dynamics
for a proprioceptive prosthesis") and Mileusnic et al. (2006), in one home.

Each experiment is a module with ``run(out_dir, quick=False, ...)`` that writes its figures
and tables into ``out_dir`` and returns a small dataclass of the numbers it reports (with
``summary_md()``). :mod:`~proprio_env.experiments.runner` runs the validation set in order
(``python scripts/validate.py``); the scripts in ``scripts/`` are thin command lines over
these modules.

=====================  ============================================  ============================
experiment             what it reproduces                            outputs (in ``out_dir``)
=====================  ============================================  ============================
``human_gains``        seed paper Sec. IV: the G x 1/5 human gains   ``human_gains.{md,csv,png}``
                       (fusimotor swing < 30 pps), HUMAN vs CAT
``ecrb``               seed paper Fig. 6: human ECRB wrist           ``ecrb_ranges.md``,
                       protocol (after Kakuda & Nagaoka 1998)        ``ecrb_protocol.png``,
                                                                     ``ecrb_length.png``
``obstruction``        seed paper Fig. 7: obstructed movement        ``obstruction_{measured,
                       (after Prochazka), template from the          intended}.png``,
                       measured vs the intended motion               ``obstruction_metrics.csv``,
                                                                     ``obstruction.md``
``spindle_accuracy``   Mileusnic 2006 Fig. 3 protocol: accuracy      ``accuracy_table.md``,
                       and stability of the integrators against      ``fig3_protocol.png``
                       the stiff reference
``length_fits``        seed paper Fig. 5: fibre length vs elbow      ``length_fits.json``,
                       angle, fits vs MuJoCo vs OpenSim              ``length_fits.png``
``demo``               seed paper Fig. 8: the whole chain on servo   ``demo.png``,
                       flexion-extension at ~130 deg/s               ``demo_signals.csv``
``chain_figures``      two chain design choices: the length          ``derivative_noise.png``,
                       low-pass under noise, the PI predictor        ``predictor_overshoot.png``
``training``           PPO on ElbowReach-v0 from the afferents,      ``eval.json``, ``curve.csv``,
                       held-out targets (docs/envs.md)               ``curve.png``, ``policy.zip``
``soak``               the envs stay finite and bounded under        (none: returns the extremes)
                       random actions (``soak(env_id, steps)``)
=====================  ============================================  ============================

The validation set (``runner.validation_steps``) is the first six, in that order.
"""
