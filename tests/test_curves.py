"""Training curves: a CSV beside each checkpoint that a continued run keeps up to where it resumed,
and `hdp plot curves` draws it."""

import csv
import math

import pytest

from hdp_eval.curves_plot import panels, plot_curves
from hdp_learning.curves import CurveLog, curves_path, read_curves

pytestmark = pytest.mark.unit


def test_rows_columns_and_a_continued_run(tmp_path):
    path = curves_path(tmp_path / 'rkd.pt')
    assert path == tmp_path / 'rkd_curves.csv'
    log = CurveLog(path)
    log.add(50, loss=0.5, lr=1e-4)
    log.add(100, loss=0.25, lr=2e-4)
    log.add(100, val_translation_cm=3.0, loss=math.nan)
    with open(path, newline='') as f:                    # plain CSV, read without this project
        rows = list(csv.reader(f))
    assert rows[0] == ['step', 'loss', 'lr', 'val_translation_cm']
    assert rows[1] == ['50', '0.5', '0.0001', ''] and rows[3] == ['100', '', '', '3.0']
    log.add(150, loss=0.2, lr=3e-4)
    continued = CurveLog(path, resume_step=100)          # resumed at 100: step 150 is redone
    continued.add(150, loss=0.1, lr=3e-4)
    columns, rows = read_curves(path)
    assert [r['step'] for r in rows] == [50, 100, 100, 150] and rows[-1]['loss'] == 0.1
    assert panels(columns) == [('losses', ['loss']), ('lr', ['lr']), ('metric', ['val_translation_cm'])]
    assert CurveLog(path).rows == []                     # a fresh run starts a fresh file


def test_plot_writes_a_png_and_refuses_a_file_that_is_not_curves(tmp_path):
    log = CurveLog(tmp_path / 'c.csv')
    for step in range(50, 501, 50):
        log.add(step, loss=1 / step, pose_loss=2 / step, lr=1e-4)
    plot_curves(tmp_path / 'c.csv', tmp_path / 'c.png')
    assert (tmp_path / 'c.png').read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    (tmp_path / 'bad.csv').write_text('a,b\n1,2\n')
    with pytest.raises(ValueError, match='not a curves file'):
        plot_curves(tmp_path / 'bad.csv', tmp_path / 'bad.png')
