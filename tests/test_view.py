"""`codesign view`: Rerun recordings of episodes, comparisons, sweeps, exports and designs, read back as
a user's viewer would see them (frames, particles, colours by muscle), and the web viewer opened in
headless Chromium (skipped where there is none) with the robot's colours on screen."""
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections import defaultdict

import imageio.v2 as imageio
import numpy as np
import pytest
from conftest import TINY_MPM_HORIZON, TINY_MPM_RECIPE

from codesign import plugins, runner
from codesign.artifacts import PALETTE
from codesign.recipe import resolve_recipe
from codesign_mpm.viewing.render import PASSIVE
from codesign_mpm.viewing.view import MAX_FIBERS, PIECE_COLORS

rrchunk = pytest.importorskip("rerun.chunk")

HORIZON = TINY_MPM_HORIZON
TINY = TINY_MPM_RECIPE


@pytest.fixture(scope="module")
def run_dir(tiny_mpm_run):
    return tiny_mpm_run


class Rrd:
    """An .rrd read back: each entity's static and per-step values of each column."""

    def __init__(self, path) -> None:
        self.static: dict[str, dict[str, list]] = defaultdict(dict)
        self.steps: dict[str, dict[str, dict[int, object]]] = defaultdict(lambda: defaultdict(dict))
        for chunk in rrchunk.RrdReader(path).stream():
            batch = chunk.to_record_batch()
            columns = {name: batch.column(name).to_pylist() for name in batch.schema.names
                       if ":" in name or name == "step"}  # components, and the control-step timeline
            for name, values in columns.items():
                if chunk.is_static:
                    self.static[chunk.entity_path][name] = values[0]
                elif "step" in columns and name != "step":
                    for step, value in zip(columns["step"], values):
                        if value is not None:
                            self.steps[chunk.entity_path][name][step] = value

    def entities(self) -> set[str]:
        return set(self.static) | set(self.steps)


def rgb(packed) -> np.ndarray:
    """Rerun's colours (0xRRGGBBAA) as (N, 3) bytes."""
    c = np.asarray(packed, dtype=np.uint64)
    return np.stack([(c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255], -1).astype(int)


def design_groups(run_dir) -> np.ndarray:
    data = np.load(run_dir / "best" / "design.npz")
    strength = np.abs(data["muscle"][data["occupancy"] >= 0.5])
    return np.where(strength.max(1) > 0, strength.argmax(1), -1)


def test_a_runs_best_episode_has_every_frame_its_particles_and_muscle_colours(run_dir, tmp_path, cli):
    out = tmp_path / "best.rrd"
    code, stdout, stderr = cli("view", str(run_dir), "--out", str(out))
    assert code == 0 and stdout.strip() == str(out) and f"rerun {out}" in stderr and "--serve-web" in stderr
    rrd, root = Rrd(out), "/run/best"
    groups = design_groups(run_dir)
    positions = rrd.steps[f"{root}/robot/action"]["Points3D:positions"]
    assert sorted(positions) == list(range(HORIZON + 1))  # frame 0 and one per control step
    assert all(len(p) == len(groups) for p in positions.values())  # every robot particle, every frame
    assert not np.allclose(positions[0], positions[HORIZON])  # it moves
    by_muscle = rgb(rrd.static[f"{root}/robot/muscle_group"]["Points3D:colors"])
    assert np.array_equal(by_muscle, PALETTE[groups])  # the tab10 colour of each particle's muscle
    actions = [rgb(c) for _, c in sorted(rrd.steps[f"{root}/robot/action"]["Points3D:colors"].items())]
    assert np.all(actions[0] == np.rint(PASSIVE * 255))  # at rest nothing acts
    assert all((a != np.rint(PASSIVE * 255)).any(1).mean() > 0.5 for a in actions[1:])  # the sine gait acts
    seen = np.concatenate(actions[1:])
    r, g, b = seen.T
    assert ((r - np.maximum(g, b)) > 40).any() and ((b - np.maximum(r, g)) > 40).any()  # red and blue: both ways
    pieces = rrd.steps[f"{root}/robot/piece"]["Points3D:colors"]
    assert all((rgb(c) == np.rint(PASSIVE * 255)).all() for c in pieces.values())  # the body stays whole
    for k in range(4):
        assert sorted(rrd.steps[f"{root}/plots/actions/muscle_{k}"]["Scalars:scalars"]) == list(range(1, HORIZON + 1))
    rewards = rrd.steps[f"{root}/plots/reward"]["Scalars:scalars"]
    assert len(rewards) == HORIZON and np.isfinite([v[0] for v in rewards.values()]).all()
    com = rrd.steps[f"{root}/com/path"]["LineStrips3D:strips"]
    assert [len(com[f][0]) for f in sorted(com)] == list(range(1, HORIZON + 2))  # the path so far
    assert "Mesh3D:vertex_positions" in rrd.static[f"{root}/terrain"]
    np.testing.assert_allclose(rrd.static[f"{root}/target/direction"]["Arrows3D:vectors"][0][1:], [0, 0], atol=1e-6)
    assert not any(e.startswith(f"{root}/cover") for e in rrd.entities())  # ground: no cover


def test_iterations_0_and_best_and_a_sweep_are_lanes_of_their_own(run_dir, tmp_path, cli):
    sweep = tmp_path / "sweep"
    for name in ("a", "b"):
        shutil.copytree(run_dir, sweep / "runs" / name)
    out = tmp_path / "sweep.rrd"
    code, stdout, _ = cli("view", str(sweep), "--iterations", "0,best", "--out", str(out))
    assert code == 0, stdout
    rrd = Rrd(out)
    roots = [f"/{run}/{it}" for run in ("a", "b") for it in ("iteration_0", "best")]
    assert all(f"{root}/robot/action" in rrd.entities() for root in roots)
    offsets = [rrd.static[root]["Transform3D:translation"][0] for root in roots]
    z = [o[2] for o in offsets]
    assert z == sorted(z) and len(set(z)) == 4 and all(o[0] == o[1] == 0 for o in offsets)  # lanes across z
    start = rrd.steps["/a/iteration_0/plots/actions/muscle_0"]["Scalars:scalars"]
    best = rrd.steps["/a/best/plots/actions/muscle_0"]["Scalars:scalars"]
    assert start != best  # iteration 0's controller is the one the run started from, not its best


def test_bad_inputs_name_the_value_and_what_is_allowed(run_dir, tmp_path, cli, toy_recipe):
    toy = runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "toy", progress=False)
    code, _, err = cli("view", str(toy))
    assert code == 1 and "no plugin can view" in err  # the MPM plugin views its own environments only
    code, _, err = cli("view", str(run_dir), "--iterations", "3", "--out", str(tmp_path / "v.rrd"))
    assert code == 1 and "'3'" in err and "best, 0" in err
    (tmp_path / "empty").mkdir()
    code, _, err = cli("view", str(tmp_path / "empty"))
    assert code == 1 and "is not a run directory" in err and "no finished run" in err
    code, _, err = cli("view", str(run_dir), "--out", str(tmp_path / "v.mp4"))
    assert code == 1 and "v.mp4" in err and ".rrd" in err
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    code, _, err = cli("view", str(tmp_path / "other.npz"))
    assert code == 1 and "neither an episode export" in err and "it has a" in err
    code, _, err = cli("view", str(run_dir / "best" / "design.npz"), "--iterations", "0")
    assert code == 1 and "is a file" in err


def test_a_design_shows_its_muscles_fibres_and_stiffness(run_dir, tmp_path, cli):
    code, stdout, _ = cli("view", str(run_dir / "best" / "design.npz"), "--out", str(tmp_path / "d.rrd"))
    assert code == 0
    rrd, groups = Rrd(tmp_path / "d.rrd"), design_groups(run_dir)
    particles = rrd.static["/run/design/particles/muscle_group"]
    assert len(particles["Points3D:positions"]) == len(groups)
    assert np.array_equal(rgb(particles["Points3D:colors"]), PALETTE[groups])
    fibers = rrd.static["/run/design/fibers"]
    assert 0 < len(fibers["Arrows3D:vectors"]) <= MAX_FIBERS
    assert len(rrd.static["/run/design/particles/stiffness"]["Points3D:colors"]) == len(groups)

    # an annotated body (`codesign annotate`): passive particles grey, no stiffness
    points = np.stack(np.meshgrid(*[np.arange(4) * 0.02] * 3, indexing="ij"), -1).reshape(-1, 3)
    labels = np.where(points[:, 0] < 0.03, 0, 1)
    labels[points[:, 1] > 0.05] = -1
    np.savez(tmp_path / "body.npz", points=points, groups=labels, fibers=np.tile([1.0, 0, 0], (len(points), 1)),
             spacing=0.02, group_names=np.array(["tail", "head"]))
    assert cli("view", str(tmp_path / "body.npz"))[0] == 0
    rrd = Rrd(tmp_path / "body.rrd")
    colors = rgb(rrd.static["/body/particles/muscle_group"]["Points3D:colors"])
    assert (colors[labels == -1] == np.rint(PASSIVE * 255)).all()
    assert (colors[labels == 1] == PALETTE[1]).all()
    assert "/body/particles/stiffness" not in rrd.entities()
    assert "1: head" in rrd.static["/body/muscle_groups"]["TextDocument:text"][0]


def test_an_export_puts_each_cover_material_in_an_entity_of_its_own(tmp_path, cli):
    """A `codesign simulate --export` file with a robot on sand and in water: the cover is hideable per
    material, and a piece of the robot moved away shows in the piece colours."""
    from codesign_mpm.materials import MATERIALS

    dx, frames = 1 / 32, 3
    block = np.stack(np.meshgrid(*[np.arange(6) * dx / 2] * 3, indexing="ij"), -1).reshape(-1, 3)
    n = len(block)
    x0 = np.concatenate([block + [0.4, 0.2, 0.3], block + [0.4, 0.1, 0.1], block + [0.6, 0.1, 0.1]])
    x = np.repeat(x0[None], frames + 1, 0).astype(np.float32)
    x[2:, :n // 6, 0] -= 10 * dx  # a slab of the robot torn off at frame 2
    material = np.r_[np.full(n, MATERIALS["neo_hookean"].id), np.full(n, MATERIALS["sand"].id),
                     np.full(n, MATERIALS["water"].id)]
    np.savez(tmp_path / "scene.npz", x=x, material=material, robot=np.arange(3 * n) < n,
             muscle=np.zeros((3 * n, 0)), actions=np.zeros((frames, 0)), dx=dx, frame_dt=0.01,
             height_map=np.full((40, 40), 0.05), body=np.zeros(3 * n, int))
    assert cli("view", str(tmp_path / "scene.npz"))[0] == 0
    rrd = Rrd(tmp_path / "scene.rrd")
    for name in ("sand", "water"):
        assert all(len(p) == n for p in rrd.steps[f"/scene/cover/{name}"]["Points3D:positions"].values())
    pieces = rrd.steps["/scene/robot/piece"]["Points3D:colors"]
    assert (rgb(pieces[1]) == np.rint(PASSIVE * 255)).all()
    torn = (rgb(pieces[2]) == np.rint(PIECE_COLORS[0] * 255)).all(1)
    assert torn.sum() == n // 6
    assert rrd.steps["/scene/plots/torn_percent"]["Scalars:scalars"][2][0] == pytest.approx(100 / 6, rel=0.05)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.slow  # about 45 s: the viewer's WebAssembly compiles and draws on a software rasterizer
@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine (apt-get install chromium)")
def test_the_web_viewer_shows_the_robot_in_headless_chromium(run_dir, tmp_path):
    """`codesign view RUN --serve` serves Rerun's bundled web viewer; headless Chromium (WebGL on
    SwiftShader, no GPU) opens it, and the robot's red and blue (its muscles acting) are on screen."""
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra")
    port, log = _free_port(), tmp_path / "serve.log"
    with log.open("w") as err:
        server = subprocess.Popen([sys.executable, "-m", "codesign", "view", str(run_dir), "--out",
                                   str(tmp_path / "web.rrd"), "--serve", "--port", str(port)],
                                  stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
                                  env={k: v for k, v in os.environ.items() if k != plugins.EXPLICIT_ENV})
    try:
        url = None
        deadline = time.monotonic() + 120
        while url is None:  # its stderr says where to open it
            assert server.poll() is None, f"the server stopped: {log.read_text()}"
            assert time.monotonic() < deadline, f"no address printed: {log.read_text()}"
            lines = [line for line in log.read_text().splitlines() if line.startswith("serving ")]
            url = lines[0].split("open ", 1)[1].split(" ")[0] if lines else None
            time.sleep(0.5)
        assert url.startswith(f"http://localhost:{port}/")
        while True:
            try:
                urllib.request.urlopen(f"http://localhost:{port}/", timeout=2)
                break
            except OSError:
                assert time.monotonic() < deadline, "the web viewer never answered"
                time.sleep(0.5)
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            shot = tmp_path / "viewer.png"
            red = blue = 0
            for _ in range(45):  # the viewer compiles its WebAssembly and loads the recording
                time.sleep(2)
                page.screenshot(path=str(shot))
                image = np.asarray(imageio.imread(shot))[..., :3].astype(int)
                r, g, b = image[..., 0], image[..., 1], image[..., 2]
                red, blue = int(((r > g + 80) & (r > b + 80)).sum()), int(((b > r + 80) & (b > g + 60)).sum())
                if red > 1500 and blue > 1500:
                    break
            browser.close()
        assert red > 1500 and blue > 1500, f"robot pixels: {red} red, {blue} blue (screenshot {shot})"
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=30)
