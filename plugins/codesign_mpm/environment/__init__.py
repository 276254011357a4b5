"""The locomotion environments on the engine: what a recipe's `environment:` builds.

    config.py        the recipe keys (`LocomotionConfig`), the eight presets and their checks
    env.py           `LocomotionEnv`: the scene of a preset, a design, episodes, the task's reward
    episode.py       an episode's two paths: open loop in one differentiable rollout, closed loop per step
    bridge.py        the torch autograd bridge to the simulator
    tasks.py         the paper's four tasks (a plugin adds its own with `register_task`)
    observations.py  what a closed-loop controller sees
    settle.py        covers and fixed bodies that start at rest under their own weight
    gym.py           every environment x task as a Gymnasium environment
    protocols.py     the small interfaces these modules share
"""
