import sympy

from rrtcolearn.systems import register
from rrtcolearn.systems.check import check_system
from rrtcolearn.systems.symbolic import build_system


def make_damped_pendulum():
    theta, omega, u = sympy.symbols("theta omega u", real=True)
    b = sympy.Symbol("b")  # viscous damping, substituted below
    return build_system(
        "damped_pendulum",
        states=[theta, omega], inputs=[u],
        drift=[omega, sympy.sin(theta) - b * omega],   # x' = a(x) + B(x) u
        input_matrix=[[0], [1]],
        input_weight=[[1]],                             # cost w + u^T R u / 2
        parameters={b: 0.1},
        state_low=[-4.712, -3.1416], state_high=[1.5708, 3.1416],
        angle_dims=[0],
        description="Pendulum with viscous damping b = 0.1",
        defaults={"start": [-3.14159, 0.0], "goal": [0.0, 0.0]},     # the query `run` plans
    )


check_system(make_damped_pendulum())        # shapes, H* = 0, u* = argmin H, ODEs, conservation
register("damped_pendulum", make_damped_pendulum)

if __name__ == "__main__":
    from rrtcolearn import pipeline
    from rrtcolearn.config import load_config

    cfg = load_config(overrides=["system.name=damped_pendulum", "generate.n_simulations=20000"])
    pipeline.generate(cfg, "runs/damped")
    pipeline.clean(cfg, "runs/damped")
    model = pipeline.fit(cfg, "runs/damped")
    plan = pipeline.plan(model, [-3.14159, 0], [0, 0], goal_tolerance=0.2, seed=1)
    print(plan.status, plan.nodes, round(plan.path_cost, 2))
