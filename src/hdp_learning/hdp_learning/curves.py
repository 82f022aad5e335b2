"""Training curves as a CSV file beside the checkpoint: a `step` column, then one column per
scalar (losses, learning rate, validation metrics), empty where a row has none. Any
spreadsheet, pandas or gnuplot opens it without this project; `hdp plot curves` draws it.
Every trainer writes one (`hdp train low-level`, `hdp train high-level`, `hdp train flat`).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path


def curves_path(checkpoint) -> Path:
    """Where a checkpoint's curves go: rkd.pt -> rkd_curves.csv beside it."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(f'{checkpoint.stem}_curves.csv')


def read_curves(path) -> tuple[list[str], list[dict]]:
    """(columns, rows) of a curves file; a row maps each column to a float, or None where empty."""
    with open(path, newline='') as f:
        reader = csv.DictReader(f)
        columns = list(reader.fieldnames or [])
        rows = [{k: (float(v) if v not in ('', None) else None) for k, v in row.items()} for row in reader]
    if not columns or columns[0] != 'step':
        raise ValueError(f'{path} is not a curves file (its first column is not "step")')
    return columns, rows


class CurveLog:
    """Appends rows to a curves file; a run that continues from ``resume_step`` keeps the rows up to
    it and writes the steps it redoes again."""

    def __init__(self, path, resume_step: int = 0):
        self.path = Path(path)
        self.columns, self.rows = ['step'], []
        if resume_step and self.path.is_file():
            columns, rows = read_curves(self.path)
            self.columns, self.rows = columns, [r for r in rows if r['step'] <= resume_step]

    def add(self, step: int, **values: float) -> None:
        """One row at ``step``; non-finite values are written empty."""
        row = {'step': float(step)}
        for name, value in values.items():
            if name not in self.columns:
                self.columns.append(name)
            row[name] = float(value) if value is not None and math.isfinite(value) else None
        self.rows.append(row)
        partial = self.path.with_name(self.path.name + '.partial')
        with open(partial, 'w', newline='') as f:
            writer = csv.writer(f)
            writer.writerow(self.columns)
            for r in self.rows:
                writer.writerow(['' if r.get(c) is None else (int(r[c]) if c == 'step' else r[c]) for c in self.columns])
        partial.replace(self.path)
