"""Example third-party codesign plugin: a controller and a material model."""
from codesign.hookspecs import hookimpl


@hookimpl
def codesign_register(registry) -> None:
    registry.add(
        "controller",
        "square_wave",
        "codesign_example_plugin.square_wave:SquareWave",
        "codesign_example_plugin.square_wave:SquareWaveConfig",
        "Bang-bang gait: each actuator switches between +/- amplitude, phase-shifted per actuator.",
    )


@hookimpl
def codesign_register_materials() -> list[str]:
    return ["codesign_example_plugin.mooney_rivlin"]
