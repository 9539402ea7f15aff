"""Training controllers on proprioceptive feedback: the Stable-Baselines3 runs (`sb3`) and
their vector-env adapter (`sb3_vec`), and the same runs on Ray RLlib (`rllib`); the command
line is ``scripts/train.py`` (docs/training.md)."""
