"""What every measurement shares: the machine it ran on, and a measurement in a process of its own.

Kept apart from the measurements (accuracy, stability, bench) and the documents written from
them, which all use it, so that none of them imports another to get it."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys


def machine_description() -> str:
    """This machine in a few words (cores, CPU model, Python, OS), as reports and records name it."""
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")),
               platform.processor()) if os.path.exists("/proc/cpuinfo") else platform.processor()
    return f"{os.cpu_count()} cores ({cpu}), Python {platform.python_version()}, {platform.system()}"



def run_module(module: str, *args: str, environment: dict | None = None) -> tuple[dict | None, str | None]:
    """Run `python -m MODULE ARGS` in a fresh process (its own Taichi program and peak memory; with
    `environment`'s variables added) and return (the JSON record it printed last, None), or (None,
    the last line of its error output)."""
    done = subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True,
                          env={**os.environ, **(environment or {})})
    if done.returncode:
        lines = done.stderr.strip().splitlines()
        return None, lines[-1] if lines else f"exit status {done.returncode}"
    return json.loads(done.stdout.strip().splitlines()[-1]), None
