"""Measurements and the documents written from them (`codesign bench`).

    machine.py    the machine a record was measured on; a measurement in a process of its own
    bench.py      engine throughput, backward cost, memory, batches, compile time, environments
    accuracy.py   error against time on reference problems (docs/accuracy.md)
    stability.py  hard cases forward and backward (docs/stability.md)
    documents.py  docs/accuracy.md and docs/stability.md written from the records
    analyses.py   the studies' point-by-point measurements (loss landscape, muscle ambiguity)

Measurements import `machine` and nothing of each other but `stability` the settings of `accuracy`;
`documents` reads both.
"""
