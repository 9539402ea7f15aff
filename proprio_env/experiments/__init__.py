"""The seed paper's validation experiments (its Section IV), each a function that computes
its numbers and draws its figure; :mod:`proprio_env.validation.runner` runs them all
(``python scripts/validate.py``).

- :mod:`~proprio_env.validation.human_gains`: how much the fusimotor model can change Ia and
  II with the HUMAN and the CAT gains (the reason for G x 1/5);
- :mod:`~proprio_env.validation.ecrb`: the human ECRB wrist protocol (the paper's Fig. 6);
- :mod:`proprio_env.obstruction`: obstructed movement (the paper's Fig. 7).
"""
