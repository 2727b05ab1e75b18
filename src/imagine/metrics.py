"""One logger for every training loop: ``record(key, value)`` then ``dump(step)`` writes a row
to a CSV file and scalars to TensorBoard (the pattern of Stable-Baselines3's logger).

Keys share one pattern, ``group/name`` (``losses/reconstruction``, ``charts/epsilon``). Rows are
appended; when a new key appears the file is rewritten, atomically, with the wider header. On
resume the file is cut back to the rows at or before the step the run resumes from, so no row is
repeated, and a last line cut short by a crash is dropped.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

from imagine.checkpoint import atomic_write_text


class MetricsLogger:
    def __init__(
        self, folder: str | Path, resume_step: int | None = None, tensorboard: bool = True
    ) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.csv_path = self.folder / "metrics.csv"
        self.rows: list[dict[str, float]] = []
        self.header: list[str] = []
        if self.csv_path.is_file():
            self.rows = [
                row
                for row in read_metrics(self.csv_path)
                if resume_step is not None and row.get("step", 0) <= resume_step
            ]
        self._rewrite()
        self.pending: dict[str, float] = {}
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(self.folder / "tensorboard"))

    def record(self, key: str, value: float) -> None:
        self.pending[key] = float(value)

    def dump(self, step: int) -> dict[str, float]:
        row = {"step": float(step), **self.pending}
        self.pending = {}
        self.rows.append(row)
        if self.writer is not None:
            for key, value in row.items():
                if key != "step":
                    self.writer.add_scalar(key, value, step)
            self.writer.flush()
        if set(row) <= set(self.header):
            with open(self.csv_path, "a", newline="") as f:
                f.write(_line(row, self.header))
        else:
            self._rewrite()
        return row

    def _rewrite(self) -> None:
        self.header = ["step", *sorted({k for row in self.rows for k in row} - {"step"})]
        text = ",".join(self.header) + "\n" + "".join(_line(r, self.header) for r in self.rows)
        atomic_write_text(self.csv_path, text)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def read_metrics(path: str | Path) -> list[dict[str, float]]:
    """Rows of a metrics CSV as dicts of floats; a row cut short by a crash is dropped."""
    with open(path, newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            return []
        rows = []
        for values in reader:
            if len(values) != len(header):
                continue
            try:
                rows.append({k: float(v) for k, v in zip(header, values, strict=True) if v != ""})
            except ValueError:
                continue
        return rows


def _line(row: dict[str, float], header: list[str]) -> str:
    buffer = io.StringIO()
    csv.writer(buffer).writerow([_fmt(row[k]) if k in row else "" for k in header])
    return buffer.getvalue()


def _fmt(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else f"{value:.6g}"
