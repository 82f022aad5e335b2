"""`hdp plot curves`: a training curves file (hdp_learning.curves) as a PNG, one panel per
kind: losses (log scale), learning rate, and each validation metric."""

from __future__ import annotations

from pathlib import Path

from hdp_learning.curves import read_curves


def panels(columns: list[str]) -> list[tuple[str, list[str]]]:
    """(kind, columns) drawn together: the losses in one panel, the learning rate, one per metric."""
    losses = [c for c in columns[1:] if c != 'lr' and not c.startswith('val_')]
    groups = [('losses', losses)] if losses else []
    groups += [('lr', ['lr'])] if 'lr' in columns else []
    return groups + [('metric', [c]) for c in columns if c.startswith('val_')]


def plot_curves(csv_path, png_path, title: str = '') -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    columns, rows = read_curves(csv_path)
    groups = panels(columns)
    if not groups:
        raise ValueError(f'{csv_path} has no curves besides the step')
    fig, axes = plt.subplots(len(groups), 1, figsize=(7, 2.4 * len(groups)), sharex=True, squeeze=False)
    for ax, (kind, names) in zip(axes[:, 0], groups):
        for name in names:
            points = [(r['step'], r[name]) for r in rows if r.get(name) is not None]
            if points:
                ax.plot(*zip(*points), label=name, marker='.' if kind == 'metric' else None)
        if kind == 'losses' and all(r[n] > 0 for r in rows for n in names if r.get(n) is not None):
            ax.set_yscale('log')
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel('step')
    fig.suptitle(title or Path(csv_path).name)
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


def configure(parser) -> None:
    """Draw a training curves CSV (written beside every checkpoint by hdp train) as a PNG."""
    parser.add_argument('csv', type=Path, help='<checkpoint stem>_curves.csv')
    parser.add_argument('--out', type=Path, required=True, help='PNG to write')
    parser.add_argument('--title', default='')
    parser.set_defaults(func=run)


def run(args) -> int:
    try:
        plot_curves(args.csv, args.out, args.title)
    except (OSError, ValueError) as err:
        raise SystemExit(f'hdp plot curves: {err}') from None
    print(f'wrote {args.out}')
    return 0
