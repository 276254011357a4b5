"""Where metrics go: a JSON-lines file always, Weights & Biases optionally.

W&B is imported only when a recipe turns it on. Its default mode here is
``offline``: the run is written under ``<run_dir>/wandb/offline-run-*`` with no
network access and can be uploaded later with ``wandb sync``.
"""

from __future__ import annotations

import json
import math
import os
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


def wandb_off(mode: str) -> bool:
    """Whether W&B is disabled, by the recipe's mode or by $WANDB_MODE: then it is not started at all
    (its init alone takes 0.4 s)."""
    return "disabled" in (mode, os.environ.get("WANDB_MODE"))


class Tracker(ABC):
    """Receives each iteration's metrics and the final summary of a run."""

    @abstractmethod
    def log(self, metrics: Mapping[str, Any], step: int) -> None: ...

    def summary(self, summary: Mapping[str, Any]) -> None:
        """Record the run's final summary; ignored by default."""

    def log_image(self, key: str, path: Path) -> None:
        """Record a picture the run made (a plot); ignored by default (the file is in the run dir)."""

    def log_video(self, key: str, path: Path) -> None:
        """Record a video the run made (its best episode); ignored by default (the file is in the run dir)."""

    def log_table(self, key: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
        """Record a table (a sweep's summary); ignored by default (the file is in the sweep dir)."""

    def close(self) -> None:
        """Flush and release; called once, also when the run fails."""


def _jsonable(value: Any) -> Any:
    """Turn numpy/torch scalars into Python numbers and non-finite floats into strings JSON accepts."""
    if hasattr(value, "item") and callable(value.item):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


class JsonlTracker(Tracker):
    """Appends one JSON object per logged step to ``metrics.jsonl``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._file = path.open("a", encoding="utf-8")

    def log(self, metrics: Mapping[str, Any], step: int) -> None:
        record = {k: _jsonable(v) for k, v in metrics.items()}
        self._file.write(json.dumps(record, default=str) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


class WandbTracker(Tracker):
    """Logs to a W&B run stored under ``run_dir`` (offline by default)."""

    def __init__(
        self,
        run_dir: Path,
        *,
        mode: str,
        project: str,
        group: str | None,
        name: str,
        config: Mapping[str, Any],
        job_type: str | None = None,
    ) -> None:
        import wandb

        self._run = wandb.init(
            mode=mode, dir=str(run_dir), project=project, group=group, name=name, config=dict(config),
            job_type=job_type,
        )

    def log(self, metrics: Mapping[str, Any], step: int) -> None:
        self._run.log(dict(metrics), step=step)

    def summary(self, summary: Mapping[str, Any]) -> None:
        self._run.summary.update(dict(summary))

    def log_image(self, key: str, path: Path) -> None:
        import wandb

        self._run.log({key: wandb.Image(str(path))})

    def log_video(self, key: str, path: Path) -> None:
        import wandb

        self._run.log({key: wandb.Video(str(path))})

    def log_table(self, key: str, columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
        import wandb

        self._run.log({key: wandb.Table(columns=list(columns), data=[list(r) for r in rows])})

    def close(self) -> None:
        self._run.finish()


class MultiTracker(Tracker):
    """Fans every call out to several trackers."""

    def __init__(self, trackers: Sequence[Tracker]) -> None:
        self.trackers = list(trackers)

    def log(self, metrics: Mapping[str, Any], step: int) -> None:
        for tracker in self.trackers:
            tracker.log(metrics, step)

    def summary(self, summary: Mapping[str, Any]) -> None:
        for tracker in self.trackers:
            tracker.summary(summary)

    def log_image(self, key: str, path: Path) -> None:
        for tracker in self.trackers:
            tracker.log_image(key, path)

    def log_video(self, key: str, path: Path) -> None:
        for tracker in self.trackers:
            tracker.log_video(key, path)

    def close(self) -> None:
        for tracker in self.trackers:
            tracker.close()
