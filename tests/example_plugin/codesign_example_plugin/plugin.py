"""Example third-party codesign plugin: one component of each kind a recipe names (a controller, a
representation, an optimizer, an MPM environment) and a material model."""
from codesign.hookspecs import hookimpl


@hookimpl
def codesign_register(registry) -> None:
    from codesign_mpm.environment.config import CoverConfig, EnvironmentPreset
    from codesign_mpm.plugin import register_environment  # light: no Taichi until a scene is built

    registry.add(
        "controller",
        "square_wave",
        "codesign_example_plugin.square_wave:SquareWave",
        "codesign_example_plugin.square_wave:SquareWaveConfig",
        "Bang-bang gait: each actuator switches between +/- amplitude, phase-shifted per actuator.",
    )
    registry.add("representation", "wedge", "codesign_example_plugin.wedge:Wedge",
                 "codesign_example_plugin.wedge:WedgeConfig", "A wedge-shaped body with one trainable slope.")
    registry.add("optimizer", "hill_climb", "codesign_example_plugin.hill_climb:HillClimb",
                 "codesign_example_plugin.hill_climb:HillClimbConfig", "Hill climbing on the controller's parameters.")
    register_environment(registry, "gravel", EnvironmentPreset(
        "Coarse gravel: a sand layer of a steeper friction angle on high-friction terrain.", friction=0.8,
        cover=CoverConfig(kind="sand", thickness=0.02, friction_angle=55.0)))


@hookimpl
def codesign_register_materials() -> list[str]:
    return ["codesign_example_plugin.mooney_rivlin"]
