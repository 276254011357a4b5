"""Progress bars: drawn on a terminal when asked for, silent otherwise (logs, CI, --no-progress)."""
import io

import pytest

from codesign import runner
from codesign.progress import progress_bar, shown
from codesign.recipe import resolve_recipe


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.mark.parametrize("tty, requested, drawn", [(True, True, True), (True, False, False), (False, True, False)])
def test_a_bar_is_drawn_only_on_a_terminal_when_requested(monkeypatch, tty, requested, drawn):
    stream = Terminal() if tty else io.StringIO()
    monkeypatch.setattr("sys.stderr", stream)
    assert shown(requested) is drawn
    assert list(progress_bar(range(3), desc="work", show=requested)) == [0, 1, 2]
    assert ("work" in stream.getvalue()) is drawn


def test_a_run_shows_its_iterations_and_eta_on_a_terminal(monkeypatch, tmp_path, toy_recipe):
    stream = Terminal()
    monkeypatch.setattr("sys.stderr", stream)
    runner.run(resolve_recipe(toy_recipe), run_dir=tmp_path / "run")
    assert "toy: 100%" in stream.getvalue() and "3/3" in stream.getvalue()
