"""The simulated SEM saving into a watched folder keeps the folder bounded (issue #25: 83
files, 24 MB in 45 s, about 1.9 GB an hour, before)."""

from __future__ import annotations

from semservo.messages import ScanRequest
from semservo.simulation.world import World
from services.fakelab.acquisition import FolderWriter


def test_the_saving_sem_keeps_its_last_frames_and_deletes_only_its_own(tmp_path):
    (tmp_path / "notes.txt").write_text("the operator's")
    writer = FolderWriter(World(speedup=100.0), tmp_path, chunks=1, chunk_pause_s=0.0, keep=3,
                          request=ScanRequest(rows=64, cols=64))
    for _ in range(7):
        writer.save_one()
    assert sorted(path.name for path in tmp_path.glob("*.tif")) == ["frame000004.tif", "frame000005.tif",
                                                                     "frame000006.tif"]
    assert (tmp_path / "notes.txt").exists() and writer.deleted == 4
    assert writer.counters["frames_deleted"] == 4 and writer.counters["frames_saved"] == 7
