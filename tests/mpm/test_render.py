"""`codesign render`: videos of a run's best episode and of a `simulate --export`, and stills, all
headless. Frames are read back and checked by colour: robot red/blue (muscle activation) or grey
(passive), orange where torn off the body, muscle-group colours in stills, and motion between frames."""
import os
import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pytest
from conftest import TINY_MPM_HORIZON, TINY_MPM_RECIPE

from codesign import plugins, runner
from codesign.artifacts import PALETTE
from codesign.recipe import resolve_recipe
from codesign_mpm.viewing.render import TORN, Recording, Renderer, episode_colors, record_run, render
from codesign_mpm.scene.spec import BodySpec, MuscleSpec, Scene, ShapeSpec, TerrainSpec
from codesign_mpm.simulate import simulate

HORIZON = TINY_MPM_HORIZON
TINY = TINY_MPM_RECIPE


@pytest.fixture(scope="module")
def run_dir(tiny_mpm_run):
    return tiny_mpm_run


def frames_of(path) -> list[np.ndarray]:
    return [np.asarray(f)[..., :3].astype(int) for f in imageio.get_reader(path)]


def count(image: np.ndarray, mask) -> int:
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    return int(mask(r, g, b).sum())


def reddish(r, g, b):
    return (r > g + 60) & (r > b + 60)


def bluish(r, g, b):
    return (b > r + 60) & (b > g + 30)


def grey(r, g, b):
    return (abs(r - g) < 14) & (abs(g - b) < 14) & (r > 100) & (r < 200)


def test_a_run_renders_to_mp4_with_activation_colours_and_motion(run_dir, tmp_path, cli, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    out = tmp_path / "episode.mp4"
    code, stdout, _ = cli("render", str(run_dir), "--out", str(out), "--camera", "side", "--fps", "10",
                          "--no-progress")
    assert code == 0 and str(out) in stdout and out.stat().st_size > 1000
    frames = frames_of(out)
    assert len(frames) == HORIZON + 1 and frames[0].shape == (480, 640, 3)
    assert count(frames[0], grey) > 500  # at rest every muscle is passive
    assert all(count(f, reddish) + count(f, bluish) > 200 for f in frames[1:])  # the sine gait acts
    below_stamp = [f[40:] for f in frames]  # leave out the time stamp, which always changes
    assert all(np.abs(a - b).sum() > 0 for a, b in zip(below_stamp, below_stamp[1:]))


def test_the_still_shows_each_muscle_group_in_its_colour_and_replays_nothing(run_dir, tmp_path):
    still = tmp_path / "design.png"
    assert render(run_dir, still=still, camera="oblique") == [still]
    assert not (run_dir / "best" / "episode.mp4").exists()
    image = imageio.imread(still)[..., :3].astype(float)
    direction = image / np.maximum(np.linalg.norm(image, axis=-1, keepdims=True), 1)
    seen = 0
    for color in PALETTE[:4].astype(float):  # the tiny robot has 2 x 2 x 1 muscle groups
        close = np.linalg.norm(direction - color / np.linalg.norm(color), axis=-1) < 0.06
        seen += int(close[60:-90].sum() > 100)  # away from the title and the legend
    assert seen >= 3  # the oblique camera sees at least three of the four groups


def orange(r, g, b):
    return (r > 170) & (g > 70) & (g < 150) & (b < 40)


def test_particles_torn_off_the_body_are_orange_and_the_label_says_how_much(run_dir):
    """The replayed episode's body stays whole; moved 10 cells away in one frame, its front tenth is a
    piece of its own: exactly those particles turn orange and the label gives their share of the mass."""
    rec = record_run(run_dir)
    robot = np.flatnonzero(rec.robot)
    assert rec.mass is not None and len(rec.mass) == len(rec.material) and (rec.mass[robot] > 0).all()
    for f in range(rec.frames + 1):  # a whole body has no torn particle
        colors, torn = episode_colors(rec, f, 1.0)
        assert torn == 0.0 and not rec.torn(f).any() and not (colors == TORN).all(1).any()
    moved = np.sort(robot[np.argsort(rec.x[2][robot, 0])[-len(robot) // 10:]])  # the front tenth of the body
    rec.x = rec.x.copy()
    rec.x[2][moved, 0] += 10 * rec.dx
    colors, torn = episode_colors(rec, 2, 1.0)
    assert np.array_equal(np.flatnonzero((colors == TORN).all(1)), moved)
    assert torn == pytest.approx(rec.mass[moved].sum() / rec.mass[robot].sum())
    renderer = Renderer(rec, "side")
    images = [renderer.frame(f) for f in (1, 2)]
    assert f"torn {100 * torn:.3g}% (orange)" in renderer.text.get_text()
    assert count(images[0], orange) == 0 and count(images[1], orange) > 50


def test_a_robot_behind_water_shows_through_it():
    """Water is a translucent veil: a grey robot block behind a water block (seen from the side) still
    shows, tinted, and a sand block in front of it hides it."""
    from codesign_mpm.materials import MATERIALS

    dx = 1 / 32
    grid = np.stack(np.meshgrid(*[np.arange(6) * dx / 2] * 3, indexing="ij"), -1).reshape(-1, 3)
    robot, cover = grid + [0.4, 0.2, 0.3], grid + [0.4, 0.2, 0.1]  # the camera looks along +z: cover in front

    def drawn(kind: str) -> np.ndarray:
        n = len(grid)
        rec = Recording(x=np.concatenate([robot, cover])[None].repeat(2, 0), actions=np.zeros((1, 0)),
                        material=np.r_[np.full(n, MATERIALS["neo_hookean"].id), np.full(n, MATERIALS[kind].id)],
                        robot=np.r_[np.ones(n, bool), np.zeros(n, bool)], muscle=np.zeros((2 * n, 0)),
                        frame_dt=8e-3, dx=dx, heights=None)
        return Renderer(rec, "side").frame(1)[40:]  # below the label, whose anti-aliased text is grey

    water, sand = drawn("water").astype(int), drawn("sand").astype(int)
    tinted = lambda r, g, b: (b > r + 15) & (b < r + 80) & (r > 60) & (r < 200)  # noqa: E731 grey seen through blue
    opaque_water = lambda r, g, b: b > r + 120  # noqa: E731 water's own colour (0.30, 0.60, 0.95)
    assert count(water, tinted) > 200 and count(water, opaque_water) == 0
    assert count(sand, grey) == 0 and count(sand, tinted) == 0


def test_eval_prints_the_replayed_bodys_integrity(run_dir, cli):
    """`codesign eval` names, besides the return, the robot mass torn off and the design's thinnest part."""
    code, out, err = cli("eval", str(run_dir))
    assert code == 0, err
    line = next(line for line in out.splitlines() if line.startswith("episode 0: return "))
    assert ", torn off 0% of the robot's mass, thinnest part " in line and line.endswith(" cells")
    assert float(line.split("thinnest part ")[1].split()[0]) >= 2


def test_eval_replays_with_changed_settings_and_names_a_bad_key(run_dir, cli):
    """`codesign eval RUN environment.cfl=...` replays the best episode at another time step (the
    check of docs/integrity.md): its return is the API's replay with that change, not the run's own;
    a key the recipe does not have is named, and so is a change that would resample the design."""
    def replayed(*changes: str) -> float:
        code, out, err = cli("eval", str(run_dir), *changes)
        assert code == 0, err
        return float(next(line for line in out.splitlines() if line.startswith("episode 0: return ")).split()[3].rstrip(","))

    cfl = runner.load_run_data(run_dir)[1].sections["environment"].config.cfl / 4
    quarter = runner.replay_best(run_dir, 1, {"environment": {"cfl": cfl}})[0].episode_return
    assert replayed(f"environment.cfl={cfl}") == pytest.approx(quarter, rel=1e-5)
    assert replayed() != pytest.approx(quarter, rel=1e-5)
    code, _, err = cli("eval", str(run_dir), "environment.cfll=0.1")
    assert code != 0 and "environment.cfll" in err
    code, _, err = cli("eval", str(run_dir), "environment.dx=0.02")  # would resample the design
    assert code != 0 and "not environment.dx" in err


def test_an_export_renders_to_gif_in_a_process_without_display(tmp_path):
    """`simulate --export` keeps what rendering needs; the render itself needs no Taichi or display."""
    scene = Scene(size=[0.6, 0.45, 0.45], dx=1 / 24, terrain=TerrainSpec(kind="flat", height=0.13), bodies=[
        BodySpec(name="robot", shape=ShapeSpec(kind="box", size=[0.15, 0.06, 0.06]), center=[0.3, 0.25, 0.22],
                 muscles=MuscleSpec(groups=[2, 1, 1]), robot=True)])
    export = tmp_path / "drop.npz"
    simulate(scene, 4, export=export, progress=False)
    data = np.load(export)
    assert {"x", "v", "material", "body", "frame_dt", "muscle", "robot", "actions", "dx", "height_map"} <= set(data)
    assert data["actions"].shape == (4, 2) and data["robot"].all()
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND", plugins.EXPLICIT_ENV)}  # no test plugin
    out = tmp_path / "drop.gif"
    done = subprocess.run([sys.executable, "-m", "codesign", "render", str(export), "--out", str(out),
                           "--no-progress"], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    frames = frames_of(out)
    assert len(frames) == 5
    assert all(count(f, grey) > 200 for f in frames)  # zero actions: a passive robot
    assert np.abs(frames[-1][40:] - frames[0][40:]).sum() > 0  # it fell


@pytest.mark.parametrize("args, message", [
    (["--camera", "front"], "--camera 'front': choose from side, top, oblique"),
    (["--out", "x.avi"], "suffix '.avi' is not supported; choose from .mp4, .gif"),
])
def test_bad_options_name_the_value_and_the_choices(tmp_path, cli, args, message):
    export = tmp_path / "x.npz"
    np.savez(export, x=np.zeros((2, 3, 3), np.float32), material=np.zeros(3, np.int32))
    code, _, err = cli("render", str(export), *args, "--no-progress")
    assert code != 0 and message in " ".join(err.split())


def test_a_path_that_is_neither_a_run_nor_an_export_is_named(tmp_path, cli):
    code, _, err = cli("render", str(tmp_path / "nothing.txt"))
    assert code == 1 and "nothing.txt" in err and "run directory" in err


def test_render_switch_writes_the_best_episode_video_when_the_run_ends(tmp_path):
    recipe = resolve_recipe({**TINY, "render": {"enabled": True, "camera": "side", "fps": 10}})
    run = runner.run(recipe, run_dir=tmp_path / "run", progress=False)
    video = run / "best" / "episode.mp4"
    assert video.stat().st_size > 1000
    assert len(frames_of(video)) == HORIZON + 1
