"""The checkpoint store: memory up to its budget, then a temporary file, read back exactly."""
import numpy as np
import pytest

from codesign_mpm.engine.checkpoints import CheckpointStore


def states(count, n=5, seed=0):
    rng = np.random.default_rng(seed)
    return [(rng.normal(size=(n, 3)).astype(np.float32), rng.normal(size=(n, 3, 3)), rng.normal(size=n))
            for _ in range(count)]


def test_checkpoints_past_the_budget_go_to_a_file_and_come_back_exactly(tmp_path):
    saved = states(6)
    record = sum(a.nbytes for a in saved[0])
    store = CheckpointStore(memory_bytes=2 * record + 1, directory=str(tmp_path))
    for state in saved:
        store.append(state)
    assert len(store) == 6 and store.spilled == 4
    for k in reversed(range(6)):  # the backward pass reads them last first
        for got, want in zip(store[k], saved[k]):
            assert got.dtype == want.dtype and got.shape == want.shape
            np.testing.assert_array_equal(got, want)
    with pytest.raises(IndexError):
        store[6]


def test_a_cleared_store_is_refilled_by_the_next_rollout():
    store = CheckpointStore(memory_bytes=0)
    for state in states(3, seed=1):
        store.append(state)
    store.clear()
    assert len(store) == 0
    again = states(2, seed=2)
    for state in again:
        store.append(state)
    assert len(store) == 2 and store.spilled == 2
    np.testing.assert_array_equal(store[1][1], again[1][1])
    with pytest.raises(ValueError, match="same arrays"):
        store.append(states(1, n=4)[0])
    store.close()
    assert len(store) == 0


def test_a_checkpoint_that_cannot_be_written_names_the_directory_and_the_remedy(tmp_path, monkeypatch):
    store = CheckpointStore(memory_bytes=0, directory=str(tmp_path))
    store.append(states(1)[0])

    def full(*args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(store._file, "write", full)
    with pytest.raises(OSError, match=f"checkpoint 1 .* to {tmp_path}: .*No space left.*CODESIGN_CHECKPOINT_DIR"):
        store.append(states(1)[0])


def test_the_default_segment_is_the_whole_episode_where_its_states_fit(monkeypatch):
    """Backward recomputes every segment but the last: within SEGMENT_MEMORY_BYTES the whole episode
    is one segment (rounded up to a power of two, so that designs whose steps differ a little share a
    layout), beyond it as many substeps as fit, never fewer than the memory-optimal sqrt(T / 2)."""
    from codesign_mpm.engine import simulator

    monkeypatch.setattr(simulator, "SEGMENT_MEMORY_BYTES", 1_001_000)  # 1,001 slots of 1,000 bytes
    assert [simulator.default_segment(n, slot_bytes=1000) for n in (6, 8, 80, 128, 129)] == [8, 8, 128, 128, 256]
    assert simulator.default_segment(600, slot_bytes=1000) == 1000  # 1,024 do not fit
    assert simulator.default_segment(5000, slot_bytes=100_000) == 50  # 9 fit: sqrt(2500)
    assert simulator.default_segment(1, slot_bytes=1000) == 1


def test_the_segments_memory_may_be_set_from_the_environment(monkeypatch):
    from codesign_mpm.engine import simulator

    monkeypatch.setenv("CODESIGN_SEGMENT_MEMORY_MB", "1")  # 1 MiB: 1,048 slots of 1,000 bytes
    assert simulator.default_segment(5000, slot_bytes=1000) == 1047
    monkeypatch.setenv("CODESIGN_SEGMENT_MEMORY_MB", "0")
    assert simulator.default_segment(5000, slot_bytes=1000) == 50  # the memory-optimal sqrt(2500)
    monkeypatch.setenv("CODESIGN_SEGMENT_MEMORY_MB", "1.5")
    with pytest.raises(ValueError, match="CODESIGN_SEGMENT_MEMORY_MB must be a whole number of megabytes.*'1.5'"):
        simulator.default_segment(5000, slot_bytes=1000)
