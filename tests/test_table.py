import numpy as np
import pandas as pd
import pytest

from ptrack.errors import UserError
from ptrack.table import TrajectoryWriter, make_table, read_table, validate, write_table


def _table():
    f = np.tile(np.arange(5), 3)
    p = np.repeat(np.arange(3), 5)
    rng = np.random.default_rng(0)
    return make_table(f, f * 0.1, p, rng.normal(size=15) * 1e-6, rng.normal(size=15) * 1e-6,
                      meta={"pixel_size": 1.03e-7, "frame_interval": 0.1, "source": "test"},
                      radius=np.full(15, 2.5e-7))


@pytest.mark.parametrize("suffix", [".parquet", ".csv"])
def test_roundtrip_keeps_data_and_metadata(tmp_path, suffix):
    df = _table()
    path = write_table(df, tmp_path / f"traj{suffix}")
    back = read_table(path)
    pd.testing.assert_frame_equal(back.reset_index(drop=True), df.reset_index(drop=True), check_dtype=False)
    meta = back.attrs["ptrack"]
    assert meta["pixel_size"] == 1.03e-7 and meta["frame_interval"] == 0.1
    assert meta["units"]["x"] == "m"


def test_validation_errors():
    df = _table()
    with pytest.raises(UserError, match="lacks required column"):
        validate(df.drop(columns=["x"]))
    with pytest.raises(UserError, match="duplicate rows for particle 0 at frame 1"):
        validate(pd.concat([df, df.iloc[[1]]]))
    bad = df.copy()
    bad.loc[3, "y"] = np.nan
    with pytest.raises(UserError, match="NaN or infinite 'y'"):
        validate(bad)
    bad = df.copy().astype({"frame": float})
    bad.loc[2, "frame"] = 1.5
    with pytest.raises(UserError, match="non-integer"):
        validate(bad)


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(UserError, match="not found"):
        read_table(tmp_path / "nope.parquet")
    p = tmp_path / "bad.parquet"
    p.write_bytes(b"not a parquet file")
    with pytest.raises(UserError, match="cannot read"):
        read_table(p)


def test_failed_write_leaves_no_file(tmp_path):
    df = _table().assign(weird=[object()] * 15)
    with pytest.raises(Exception):
        write_table(df, tmp_path / "x.parquet")
    assert list(tmp_path.iterdir()) == []


def test_streaming_writer_keeps_work_on_failure(tmp_path):
    df = _table()
    path = tmp_path / "sim.parquet"
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(path, {"frame_interval": 0.1}) as w:
            w.append(df[df.frame < 2])
            w.append(df[df.frame >= 2])
            raise RuntimeError("blow-up at step 7")
    back = read_table(path)
    assert len(back) == 15
    assert "blow-up" in back.attrs["ptrack"]["incomplete"]
    assert back.attrs["ptrack"]["frame_interval"] == 0.1
    assert not (tmp_path / "sim.parquet.part").exists()


def test_streaming_writer_complete_table_is_not_marked(tmp_path):
    df = _table()
    with TrajectoryWriter(tmp_path / "ok.parquet", {"frame_interval": 0.1}) as w:
        w.append(df)
    back = read_table(tmp_path / "ok.parquet")
    assert "incomplete" not in back.attrs["ptrack"] and len(back) == len(df)


def test_streaming_writer_that_cannot_write_leaves_the_previous_file(tmp_path, monkeypatch):
    """A write error (e.g. a full disk) in the file itself: no footer-less .part, previous table kept."""
    import errno

    import pyarrow.parquet as pq

    df = _table()
    path = tmp_path / "sim.parquet"
    write_table(df[df.frame < 1], path)  # the previous run's table
    before = path.read_bytes()
    w = TrajectoryWriter(path, {})
    w.append(df[df.frame < 2])
    real = pq.ParquetWriter.write_table

    def full(self, table, *a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pq.ParquetWriter, "write_table", full)
    with pytest.raises(OSError):
        w.append(df[df.frame >= 2])
    monkeypatch.setattr(pq.ParquetWriter, "write_table", real)
    with pytest.raises(OSError):
        w.close(failed="OSError: no space")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sim.parquet"]


def test_written_files_honour_the_umask(tmp_path):
    import os
    import stat

    old = os.umask(0o022)
    try:
        write_table(_table(), tmp_path / "a.parquet")
        write_table(_table(), tmp_path / "a.csv")
        with TrajectoryWriter(tmp_path / "s.parquet") as w:
            w.append(_table())
        for name in ("a.parquet", "a.csv", "s.parquet"):
            assert stat.S_IMODE((tmp_path / name).stat().st_mode) == 0o644, name
    finally:
        os.umask(old)
