"""Run records in SQLite (the embedded default): runs, iterations, stage commands and
events, written as a run goes (one transaction per row, WAL journal) so a crash loses
at most the row being written, and read back after any restart.

Rows keep the controller's own JSON record beside the columns people query by, so a
record is never narrowed to what the schema foresaw.
"""

from __future__ import annotations

import csv
import io
import json
import sqlite3
import threading
import time
from pathlib import Path

import numpy as np

SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    reference_id TEXT,
    started_at_ns INTEGER NOT NULL,
    finished_at_ns INTEGER,
    state TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    iterations INTEGER NOT NULL DEFAULT 0,
    final_error_px REAL,
    settings TEXT NOT NULL,
    reference TEXT,
    outcome TEXT,
    truth TEXT
);
CREATE TABLE IF NOT EXISTS iterations (
    run_id TEXT NOT NULL REFERENCES runs(id),
    seq INTEGER NOT NULL,
    iteration INTEGER NOT NULL,
    action TEXT NOT NULL,
    t_ns INTEGER NOT NULL,
    record TEXT NOT NULL,
    PRIMARY KEY (run_id, seq, action)
);
CREATE TABLE IF NOT EXISTS stage_commands (
    run_id TEXT NOT NULL REFERENCES runs(id),
    position INTEGER NOT NULL,
    entry TEXT NOT NULL,
    PRIMARY KEY (run_id, position)
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id TEXT,
    t_ns INTEGER NOT NULL,
    kind TEXT NOT NULL,
    data TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS refs (
    id TEXT PRIMARY KEY,
    taught_at_ns INTEGER NOT NULL,
    reference TEXT NOT NULL,
    truth TEXT
);
CREATE TABLE IF NOT EXISTS targets (
    name TEXT PRIMARY KEY,
    note TEXT NOT NULL DEFAULT '',
    created_at_ns INTEGER NOT NULL,
    reference TEXT NOT NULL,
    stage TEXT NOT NULL,
    acquisition TEXT NOT NULL,
    truth TEXT,
    dtype TEXT NOT NULL,
    shape TEXT NOT NULL,
    pixels BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS iterations_by_run ON iterations(run_id, iteration);
"""

#: Columns of a run's CSV: one row per iteration, the paper's Fig. 9 quantities.
CSV_COLUMNS = ("iteration", "seq", "action", "t_ns", "dx_px", "dy_px", "rotation_deg", "error_px", "cost", "gain",
               "confidence", "snr_db", "move_x_um", "move_y_um", "voltage_x", "voltage_y", "latency_ms",
               "alpha_deg", "beta_deg", "tilt_action", "turn_rotation_deg", "turn_tilt_x_deg", "turn_tilt_y_deg")

FINISHED = ("converged", "failed", "stopped")


class RunStore:
    """Thread-safe (one connection, one lock): the gateway's event thread writes while
    request threads read."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self.lock = threading.Lock()
        self.db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self.db.row_factory = sqlite3.Row
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable across a process crash
        self.db.executescript(SCHEMA)

    def close(self) -> None:
        with self.lock:
            self.db.close()

    # -- writing --------------------------------------------------------------
    def start_run(self, run_id: str, *, started_at_ns: int, settings: dict, reference: dict | None) -> None:
        with self.lock:
            self.db.execute(
                "INSERT OR IGNORE INTO runs (id, reference_id, started_at_ns, state, settings, reference) "
                "VALUES (?, ?, ?, 'servoing', ?, ?)",
                (run_id, reference and reference.get("id"), started_at_ns, json.dumps(settings), json.dumps(reference)))

    def add_iteration(self, run_id: str, record: dict) -> None:
        with self.lock:
            self.db.execute(
                "INSERT OR IGNORE INTO iterations (run_id, seq, iteration, action, t_ns, record) VALUES (?, ?, ?, ?, ?, ?)",
                (run_id, int(record.get("seq", -1)), int(record.get("iteration", 0)), str(record.get("action", "")),
                 int(record.get("t_ns", 0)), json.dumps(record)))
            self.db.execute("UPDATE runs SET iterations = MAX(iterations, ?) WHERE id = ?",
                            (int(record.get("iteration", 0)), run_id))

    def add_event(self, run_id: str | None, t_ns: int, kind: str, data: dict) -> None:
        with self.lock:
            self.db.execute("INSERT INTO events (run_id, t_ns, kind, data) VALUES (?, ?, ?, ?)",
                            (run_id, t_ns, kind, json.dumps(data)))

    def save_reference(self, reference: dict, truth: dict | None, taught_at_ns: int) -> None:
        """A taught reference and, on simulated hardware, the true pose it was taught at:
        kept so a gateway restarted mid-run can still give that run its truth."""
        with self.lock:
            self.db.execute("INSERT OR REPLACE INTO refs (id, taught_at_ns, reference, truth) VALUES (?, ?, ?, ?)",
                            (reference["id"], taught_at_ns, json.dumps(reference), json.dumps(truth)))

    def reference(self, reference_id: str | None = None) -> tuple[dict, dict | None] | None:
        """(reference, truth) by id, or the last taught."""
        with self.lock:
            row = (self.db.execute("SELECT reference, truth FROM refs WHERE id = ?", (reference_id,)).fetchone()
                   if reference_id is not None else
                   self.db.execute("SELECT reference, truth FROM refs ORDER BY taught_at_ns DESC LIMIT 1").fetchone())
        if row is None:
            return None
        return json.loads(row["reference"]), json.loads(row["truth"]) if row["truth"] else None

    def incomplete_runs(self) -> list[dict]:
        """Runs whose record is not complete yet: still servoing, finished only
        provisionally by the gateway, missing their stage command log, or waiting for
        the simulator's truth."""
        with self.lock:
            rows = self.db.execute(
                "SELECT id, state, started_at_ns, finished_at_ns, outcome FROM runs WHERE state = 'servoing' "
                "OR json_extract(outcome, '$.provisional') OR json_extract(outcome, '$.stage_log_error') IS NOT NULL "
                "OR json_extract(outcome, '$.truth_pending')"
            ).fetchall()
        return [{**{key: row[key] for key in row.keys()}, "outcome": json.loads(row["outcome"]) if row["outcome"]
                 else None} for row in rows]

    def set_stage_log(self, run_id: str, stage_log: list[dict], outcome: dict) -> None:
        with self.lock:
            self.db.execute("BEGIN")
            self.db.execute("DELETE FROM stage_commands WHERE run_id = ?", (run_id,))
            self.db.executemany("INSERT INTO stage_commands (run_id, position, entry) VALUES (?, ?, ?)",
                                [(run_id, index, json.dumps(entry)) for index, entry in enumerate(stage_log)])
            self.db.execute("UPDATE runs SET outcome = ? WHERE id = ?", (json.dumps(outcome), run_id))
            self.db.execute("COMMIT")

    def finish_run(self, run_id: str, *, outcome: dict, final_error_px: float | None, stage_log: list[dict],
                   truth: dict | None) -> None:
        with self.lock:
            self.db.execute("BEGIN")
            self.db.execute(
                "UPDATE runs SET state = ?, reason = ?, finished_at_ns = ?, iterations = MAX(iterations, ?), "
                "final_error_px = ?, outcome = ?, truth = ? WHERE id = ?",
                (outcome["state"], outcome.get("reason", ""), outcome.get("finished_at_ns"),
                 int(outcome.get("iterations", 0)), final_error_px, json.dumps(outcome), json.dumps(truth), run_id))
            if stage_log:
                self.db.execute("DELETE FROM stage_commands WHERE run_id = ?", (run_id,))
                self.db.executemany("INSERT INTO stage_commands (run_id, position, entry) VALUES (?, ?, ?)",
                                    [(run_id, index, json.dumps(entry)) for index, entry in enumerate(stage_log)])
            self.db.execute("COMMIT")

    # -- reading --------------------------------------------------------------
    def is_finished(self, run_id: str) -> bool:
        with self.lock:
            row = self.db.execute("SELECT state FROM runs WHERE id = ?", (run_id,)).fetchone()
        return row is not None and row["state"] in FINISHED

    def is_complete(self, run_id: str) -> bool:
        """Finished, and not only provisionally (a complete record came from the controller)."""
        with self.lock:
            row = self.db.execute("SELECT state, outcome FROM runs WHERE id = ?", (run_id,)).fetchone()
        if row is None or row["state"] not in FINISHED:
            return False
        outcome = json.loads(row["outcome"]) if row["outcome"] else {}
        return not (outcome.get("provisional") or outcome.get("stage_log_error") or outcome.get("truth_pending"))

    def exists(self, run_id: str) -> bool:
        with self.lock:
            return self.db.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is not None

    def list_runs(self, limit: int = 100, offset: int = 0) -> list[dict]:
        with self.lock:
            rows = self.db.execute(
                "SELECT id, reference_id, started_at_ns, finished_at_ns, state, reason, iterations, final_error_px, "
                "truth, settings, outcome FROM runs ORDER BY started_at_ns DESC LIMIT ? OFFSET ?",
                (limit, offset)).fetchall()
        return [_summary({key: row[key] for key in row.keys()}) for row in rows]

    def get_run(self, run_id: str) -> dict | None:
        with self.lock:
            row = self.db.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                return None
            iterations = self.db.execute(
                "SELECT record FROM iterations WHERE run_id = ? ORDER BY iteration, t_ns", (run_id,)).fetchall()
            commands = self.db.execute(
                "SELECT entry FROM stage_commands WHERE run_id = ? ORDER BY position", (run_id,)).fetchall()
        run = _summary({key: row[key] for key in row.keys()})
        run["reference"] = json.loads(row["reference"]) if row["reference"] else None
        run["trajectory"] = [json.loads(r["record"]) for r in iterations]
        run["stage_commands"] = [json.loads(r["entry"]) for r in commands]
        return run

    # -- stored targets -------------------------------------------------------
    def save_target(self, *, name: str, note: str, created_at_ns: int, reference: dict, stage: dict,
                    acquisition: dict, truth: dict | None, pixels: np.ndarray) -> None:
        pixels = np.ascontiguousarray(pixels)
        with self.lock:
            self.db.execute(
                "INSERT OR REPLACE INTO targets (name, note, created_at_ns, reference, stage, acquisition, truth, "
                "dtype, shape, pixels) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (name, note, created_at_ns, json.dumps(reference), json.dumps(stage), json.dumps(acquisition),
                 json.dumps(truth), str(pixels.dtype), json.dumps(list(pixels.shape)), pixels.tobytes()))

    def targets(self) -> list[dict]:
        with self.lock:
            rows = self.db.execute("SELECT name, note, created_at_ns, reference, stage, acquisition FROM targets "
                                   "ORDER BY created_at_ns DESC").fetchall()
        return [_target(row) for row in rows]

    def target(self, name: str) -> dict | None:
        with self.lock:
            row = self.db.execute("SELECT name, note, created_at_ns, reference, stage, acquisition FROM targets "
                                  "WHERE name = ?", (name,)).fetchone()
        return None if row is None else _target(row)

    def target_pixels(self, name: str) -> np.ndarray | None:
        with self.lock:
            row = self.db.execute("SELECT dtype, shape, pixels FROM targets WHERE name = ?", (name,)).fetchone()
        if row is None:
            return None
        return np.frombuffer(row["pixels"], dtype=np.dtype(row["dtype"])).reshape(json.loads(row["shape"])).copy()

    def target_truth(self, name: str) -> dict | None:
        with self.lock:
            row = self.db.execute("SELECT truth FROM targets WHERE name = ?", (name,)).fetchone()
        return json.loads(row["truth"]) if row is not None and row["truth"] else None

    def delete_target(self, name: str) -> None:
        with self.lock:
            self.db.execute("DELETE FROM targets WHERE name = ?", (name,))

    def csv(self, run_id: str) -> str | None:
        """One row per iteration: the paper's Fig. 9 quantities."""
        run = self.get_run(run_id)
        if run is None:
            return None
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(CSV_COLUMNS)
        for record in run["trajectory"]:
            move = record.get("move") or {}
            voltages = record.get("voltages") or {}
            turn = record.get("turn_deg") or {}
            writer.writerow([record.get("iteration"), record.get("seq"), record.get("action"), record.get("t_ns"),
                             record.get("dx_px"), record.get("dy_px"), record.get("rotation_deg"),
                             record.get("error_px"), record.get("cost"), record.get("gain"), record.get("confidence"),
                             record.get("snr_db"), move.get("x_um"), move.get("y_um"), voltages.get("x"),
                             voltages.get("y"), record.get("latency_ms"), record.get("alpha_deg"),
                             record.get("beta_deg"), record.get("tilt_action"), turn.get("rotation_deg"),
                             turn.get("tilt_x_deg"), turn.get("tilt_y_deg")])
        return out.getvalue()


#: What a run's summary takes from its outcome.
OUTCOME_IN_SUMMARY = ("fresh_frames", "partial_frames", "time_to_target_s", "source_time_to_target_s")


def _summary(row: dict) -> dict:
    """A run's row as the API lists it: its columns, with the DOFs and duration that
    people sort and read runs by."""
    settings = json.loads(row.pop("settings")) if row.get("settings") else {}
    outcome = json.loads(row["outcome"]) if row.get("outcome") else None
    truth = row.get("truth")
    end_ns = row["finished_at_ns"] or (time.time_ns() if row["state"] == "servoing" else None)
    return {**row, "settings": settings, "outcome": outcome,
            "truth": json.loads(truth) if isinstance(truth, str) else truth,
            "dofs": list(settings.get("dofs") or []),
            "duration_s": None if end_ns is None else round((end_ns - row["started_at_ns"]) / 1e9, 3),
            **{name: (outcome or {}).get(name) for name in OUTCOME_IN_SUMMARY}}


def _target(row) -> dict:
    from urllib.parse import quote

    name = row["name"]
    path = quote(name, safe="")
    return {"name": name, "note": row["note"], "created_at_ns": row["created_at_ns"],
            "reference": json.loads(row["reference"]), "stage": json.loads(row["stage"]),
            "acquisition": json.loads(row["acquisition"]), "thumbnail_url": f"/targets/{path}/thumbnail.png",
            "export_url": f"/targets/{path}/export"}
