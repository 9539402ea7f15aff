"""MuJoCo side of the proprioception toolkit: the Arm26 elbow model, its exact muscle lengths
and the Gymnasium envs.

Kept light on purpose: importing the package does not import MuJoCo or the env modules. It
registers two Gymnasium ids by their entry-point strings (``proprio_env.envs`` is imported
only when ``gymnasium.make`` builds one):

- ``proprio_env/ElbowReach-v0``: muscle-driven elbow, spindle afferents as observation;
- ``proprio_env/ProsthesisElbow-v0``: servo-driven prosthetic elbow, afferents through the
  encoder chain;
- ``-v1`` of both: the same with Ib (Golgi tendon organs) of both muscles observed too.
"""

from proprio_env.body.model import JOINT, MUSCLES, model_path

RATE_SCALE_PPS = 100.0
"""Afferent and fusimotor rates enter every observation (the envs', the wrappers' default)
divided by this (pps)."""

__all__ = ["ENV_IDS", "ID_KWARGS", "JOINT", "MUSCLES", "RATE_SCALE_PPS", "VECTOR_ENTRY_POINTS",
           "model_path", "register_envs"]

ENV_IDS = {
    "proprio_env/ElbowReach-v0": "proprio_env.envs.elbow_reach:ElbowReachEnv",
    "proprio_env/ProsthesisElbow-v0": "proprio_env.envs.prosthesis_elbow:ProsthesisElbowEnv",
    "proprio_env/ElbowReach-v1": "proprio_env.envs.elbow_reach:ElbowReachEnv",
    "proprio_env/ProsthesisElbow-v1": "proprio_env.envs.prosthesis_elbow:ProsthesisElbowEnv",
}
VECTOR_ENTRY_POINTS = {
    "proprio_env/ElbowReach-v0": "proprio_env.envs.vector:ElbowReachVectorEnv",
    "proprio_env/ProsthesisElbow-v0": "proprio_env.envs.vector:ProsthesisElbowVectorEnv",
    "proprio_env/ElbowReach-v1": "proprio_env.envs.vector:ElbowReachVectorEnv",
    "proprio_env/ProsthesisElbow-v1": "proprio_env.envs.vector:ProsthesisElbowVectorEnv",
}
ID_KWARGS = {
    "proprio_env/ElbowReach-v1": {"include_ib": True},
    "proprio_env/ProsthesisElbow-v1": {"include_ib": True},
}
"""What a version changes: v1 observes Ib (tendon organs) of both muscles (``include_ib``
defaults to True there, False in v0, whose observation is unchanged)."""
"""What ``gymnasium.make_vec(id, num_envs=n)`` builds: native vector envs (one physics call and
one batched chain call per step for all n envs)."""
MAX_EPISODE_STEPS = 200
"""Truncation of the registered envs: 200 steps, 4 s at the default 50 Hz."""


def register_envs() -> None:
    """Register :data:`ENV_IDS` with Gymnasium (idempotent; done on import)."""
    try:
        import gymnasium
    except ImportError:  # gymnasium is a core dependency; tolerate its absence for model use
        return
    for env_id, entry_point in ENV_IDS.items():
        if env_id not in gymnasium.registry:
            gymnasium.register(id=env_id, entry_point=entry_point,
                               vector_entry_point=VECTOR_ENTRY_POINTS[env_id],
                               max_episode_steps=MAX_EPISODE_STEPS,
                               kwargs=dict(ID_KWARGS.get(env_id, {})))


register_envs()
