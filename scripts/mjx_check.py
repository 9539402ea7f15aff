"""Does MJX (MuJoCo's JAX port) simulate the bundled elbow as MuJoCo's C engine does?

    pip install mujoco-mjx "jax[cpu]"      # (a venv of its own: not a dependency of ours)
    python scripts/mjx_check.py [--steps 500]

The first step of the GPU plan in ``docs/scaling.md``: before the physics of thousands of
envs moves to MJX, check that MJX accepts ``models/elbow.xml`` (spatial tendons wrapping
cylinders, MuJoCo muscles, a position servo) and reproduces the C engine. For each actuator
setting of the two envs it compares, from the same state, ``mj_forward`` (tendon lengths,
actuator forces) and ``--steps`` steps of 2 ms (the elbow angle) in float64, on whatever
device JAX finds (CPU is enough for the check). The last line:
``mjx_max_tendon_length_error_m=<float> mjx_max_angle_error_rad=<float>``, over the settings
MJX supports.
"""

from __future__ import annotations

import argparse

import numpy as np

SETTINGS = (
    # (label, model.opt.disableactuator, ctrl (BRA, TRImed, servo))
    ("servo holding 0.8 rad, muscles off", 0, (0.0, 0.0, 0.8)),
    ("servo and muscles (0.6, 0.2)", 0, (0.6, 0.2, 0.8)),
    ("ElbowReach: servo group disabled, muscles (0.6, 0.2)", 1 << 2, (0.6, 0.2, 0.0)),
)


def compare(model_path: str, disable: int, ctrl: tuple[float, ...], steps: int
            ) -> tuple[float, float, float]:
    """(max |tendon length| difference after forward (m), max |actuator force| difference
    after forward (N), max |elbow angle| difference over ``steps`` steps (rad))."""
    import jax
    import mujoco
    from mujoco import mjx

    model = mujoco.MjModel.from_xml_path(model_path)
    model.opt.disableactuator = disable
    model_x = mjx.put_model(model)
    data = mujoco.MjData(model)
    data.qpos[0] = 0.8
    data.ctrl[:] = ctrl
    mujoco.mj_forward(model, data)
    data_x = jax.jit(mjx.forward)(model_x, mjx.put_data(model, data))
    tendon = float(np.abs(np.asarray(data_x.ten_length) - data.ten_length).max())
    force = float(np.abs(np.asarray(data_x.actuator_force) - data.actuator_force).max())
    step = jax.jit(mjx.step)
    angle = 0.0
    for _ in range(steps):
        mujoco.mj_step(model, data)
        data_x = step(model_x, data_x)
        angle = max(angle, abs(float(data.qpos[0]) - float(data_x.qpos[0])))
    return tendon, force, angle


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=500)
    args = parser.parse_args(argv)
    try:
        import jax
        from mujoco import mjx  # noqa: F401
    except ImportError as exc:
        raise SystemExit(f"needs mujoco-mjx and jax ({exc}); see the docstring") from exc
    jax.config.update("jax_enable_x64", True)
    from proprio_env.body.model import model_path

    supported = []
    for label, disable, ctrl in SETTINGS:
        tendon, force, angle = compare(str(model_path()), disable, ctrl, args.steps)
        print(f"{label}: forward |d tendon length| {tendon:.2e} m, |d actuator force| "
              f"{force:.2e} N; max |d angle| over {args.steps} steps {angle:.2e} rad")
        if force < 1e-6:
            supported.append((tendon, angle))
        else:
            print("  -> MJX does not honour this setting (opt.disableactuator): a GPU port "
                  "must remove the disabled actuators from the model instead")
    print(f"mjx_max_tendon_length_error_m={max(t for t, _ in supported):.3e} "
          f"mjx_max_angle_error_rad={max(a for _, a in supported):.3e}")


if __name__ == "__main__":
    main()
