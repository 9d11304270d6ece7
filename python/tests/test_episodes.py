"""The episodes format (drivesim.episodes): round trips, checks, atomic and repeatable writes,
mirror images."""

import json

import numpy as np
import pytest

from drivesim import episodes


def make_episodes(n=6, starts=(0, 4)):
    rng = np.random.default_rng(0)
    return episodes.Episodes(
        rng.integers(0, 256, (n, 8, 16, 3), dtype=np.uint8),
        rng.standard_normal((n, 2)).astype(np.float32),
        np.array(starts, dtype=np.int64),
    )


@pytest.mark.parametrize("name", ["e.safetensors", "e.safetensors.gz"])
def test_episodes_round_trip(tmp_path, name):
    e = make_episodes()
    episodes.write(tmp_path / name, e, {"note": "x"})
    back = episodes.read(tmp_path / name)
    for k in ("frames", "actions", "episode_starts"):
        np.testing.assert_array_equal(getattr(back, k), getattr(e, k))
    assert back.bounds() == [(0, 4), (4, 6)]


@pytest.mark.parametrize("change, message", [
    (dict(starts=(1, 4)), "begin at 0"),
    (dict(starts=(0, 4, 4)), "strictly increasing"),
    (dict(starts=(0, 6)), "past the last frame"),
])
def test_episodes_reject_bad_starts(change, message):
    with pytest.raises(episodes.EpisodesError, match=message):
        make_episodes(**change)


def test_episodes_reject_bad_arrays():
    e = make_episodes()
    with pytest.raises(episodes.EpisodesError, match="uint8"):
        episodes.Episodes(e.frames.astype(np.float32), e.actions, e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match=r"\[6,2\]"):
        episodes.Episodes(e.frames, e.actions[:5], e.episode_starts)


def test_episodes_from_lists():
    # Lists are converted to the format's dtypes when no value changes, and rejected otherwise.
    e = make_episodes()
    back = episodes.Episodes(e.frames.tolist(), e.actions.tolist(), [0, 4])
    for k in ("frames", "actions", "episode_starts"):
        np.testing.assert_array_equal(getattr(back, k), getattr(e, k))
        assert getattr(back, k).dtype == getattr(e, k).dtype
    with pytest.raises(episodes.EpisodesError, match="frames: values do not fit uint8"):
        episodes.Episodes((e.frames.astype(np.int64) + 256).tolist(), e.actions, e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match="episode_starts: values do not fit int64"):
        episodes.Episodes(e.frames, e.actions, [0, 4.5])
    with pytest.raises(episodes.EpisodesError, match="actions: not a regular array"):
        episodes.Episodes(e.frames, [[1.0, 2.0], [3.0]], e.episode_starts)
    with pytest.raises(episodes.EpisodesError, match="actions must be numbers"):
        episodes.Episodes(e.frames, [["a", "b"]] * 6, e.episode_starts)


def test_episodes_read_errors(tmp_path):
    with pytest.raises(episodes.EpisodesError, match="no such file"):
        episodes.read(tmp_path / "missing.safetensors")
    (tmp_path / "junk.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(episodes.EpisodesError, match="not a"):
        episodes.read(tmp_path / "junk.safetensors")


def test_a_failed_write_leaves_the_old_file_whole(tmp_path, monkeypatch):
    """A write that fails (here: the disk full when the data is flushed) leaves the file that was
    there as it was, and no temporary file beside it."""
    path = tmp_path / "data.safetensors.gz"
    old = make_episodes()
    episodes.write(path, old)

    def full_disk(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(episodes._files.os, "fsync", full_disk)
    with pytest.raises(OSError, match=r"cannot write .*data.safetensors.gz: No space left"):
        episodes.write(path, make_episodes(n=9, starts=(0, 3, 5)))
    monkeypatch.undo()
    back = episodes.read(path)
    np.testing.assert_array_equal(back.frames, old.frames)
    np.testing.assert_array_equal(back.episode_starts, old.episode_starts)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_written_files_are_the_same_bytes_for_the_same_data(tmp_path):
    """safetensors writes its metadata in a hash map's order and gzip a time stamp: a file written
    twice differed. Sorted and without the stamp, the same episodes are the same bytes."""
    metadata = {f"key{i}": f"value {i}" for i in range(8)}
    for name in ("a.safetensors", "b.safetensors", "a.safetensors.gz", "b.safetensors.gz"):
        episodes.write(tmp_path / name, make_episodes(), metadata)
    assert (tmp_path / "a.safetensors").read_bytes() == (tmp_path / "b.safetensors").read_bytes()
    assert (tmp_path / "a.safetensors.gz").read_bytes() == (tmp_path / "b.safetensors.gz").read_bytes()
    blob = (tmp_path / "a.safetensors").read_bytes()
    header = json.loads(blob[8:8 + int.from_bytes(blob[:8], "little")])
    assert list(header["__metadata__"]) == sorted(metadata)
    assert episodes.metadata(tmp_path / "a.safetensors.gz") == metadata


@pytest.mark.parametrize("extras", [False, True])
def test_written_files_are_what_safetensors_and_gzip_write(tmp_path, extras):
    """`write` streams the file (safetensors' own `save` holds three copies of the data and ran a
    190,000-frame join out of 24 GB): the bytes are still `save`'s, with the metadata sorted, and
    gzip's `compress` of them; a strided array (a mirror image's frames) is written as its values."""
    import gzip

    from safetensors.numpy import save

    data = make_episodes(n=7, starts=(0, 3, 5))
    data.frames = data.frames[:, :, ::-1]  # not contiguous
    tensors = {"frames": np.ascontiguousarray(data.frames), "actions": data.actions,
               "episode_starts": data.episode_starts}
    if extras:
        data.rewards = {"reward": np.linspace(-1, 3, 7, dtype=np.float32), "tiles": np.arange(7, dtype=np.int32),
                        "on_road": np.array([1, 0, 1, 1, 0, 1, 1], np.uint8)}
        data.labels = np.full((7, 2), 0.5, np.float32)
        tensors.update(data.rewards, labels=data.labels)
    metadata = {"zeta": "1", "alpha": "long " * 5, "mid": "ü"}
    expected = episodes.sort_metadata(save(tensors, metadata=metadata))
    episodes.write(tmp_path / "e.safetensors", data, metadata)
    episodes.write(tmp_path / "e.safetensors.gz", data, metadata)
    assert (tmp_path / "e.safetensors").read_bytes() == expected
    assert (tmp_path / "e.safetensors.gz").read_bytes() == gzip.compress(expected, compresslevel=6, mtime=0)
    np.testing.assert_array_equal(episodes.read(tmp_path / "e.safetensors.gz").frames, data.frames)


def test_mirror_images_flip_the_frames_and_negate_the_steering():
    data = make_episodes()
    both = data.with_mirror_images()
    n = len(data.frames)
    assert both.bounds() == data.bounds() + [(s + n, e + n) for s, e in data.bounds()]
    assert np.array_equal(both.frames[:n], data.frames)
    assert np.array_equal(both.frames[n:, :, 0], data.frames[:, :, -1])  # the left column was the right
    assert np.array_equal(both.actions[n:, 0], data.actions[:, 0])
    assert np.array_equal(both.actions[n:, 1], -data.actions[:, 1])
    assert np.array_equal(both.with_mirror_images().frames[3 * n:], data.frames)  # twice: the original


def test_join_keeps_the_metadata_its_files_share(tmp_path):
    """What every file says alike stays (`python -m drivesim branches`' layout, which `train.py
    steering` checks); what they say differently goes."""
    for name, driver in (("h.safetensors", "hard"), ("e.safetensors", "expert")):
        episodes.write(tmp_path / name, make_episodes(), {"branches": "3", "horizon": "20", "driver": driver,
                                                          "source": "branches"})
    episodes.join([tmp_path / "h.safetensors", tmp_path / "e.safetensors"], tmp_path / "he.safetensors")
    assert episodes.metadata(tmp_path / "he.safetensors") == {
        "branches": "3", "horizon": "20", "source": "branches + branches", "joined": "h.safetensors,e.safetensors"}


def test_join_keeps_the_order_and_says_what_was_joined(tmp_path, capsys):
    a, b = make_episodes(), make_episodes(n=5, starts=(0, 2, 3))
    episodes.write(tmp_path / "a.safetensors", a, {"source": "first"})
    episodes.write(tmp_path / "b.safetensors.gz", b)
    out = tmp_path / "ab.safetensors.gz"
    assert episodes.main([str(tmp_path / "a.safetensors"), str(tmp_path / "b.safetensors.gz"), "--out", str(out)]) == 0
    assert "5 episodes, 11 frames" in capsys.readouterr().out
    joined = episodes.read(out)
    np.testing.assert_array_equal(joined.frames, np.concatenate([a.frames, b.frames]))
    np.testing.assert_array_equal(joined.episode_starts, [0, 4, 6, 8, 9])
    assert episodes.metadata(out) == {"source": "first + b.safetensors.gz", "joined": "a.safetensors,b.safetensors.gz"}
    with pytest.raises(SystemExit):  # a file that is not there: an error, no file written
        episodes.main([str(tmp_path / "nope.safetensors"), "--out", str(tmp_path / "x.safetensors")])
    assert not (tmp_path / "x.safetensors").exists()
