"""shadow_evaluate's outputs: JSON report, printed summary, PNG figures (atomically).

Design notes: docs/design/evaluation.md"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam_core.files import write_atomically
from slam_evaluation.plotting import render_png

STATUS_COLOURS = {'PENDING': 'tab:red', 'STATIC': 'tab:blue', 'DYNAMIC': 'tab:green'}
STATUS_CODES = {'PENDING': 0, 'STATIC': 1, 'DYNAMIC': 2}  # the core's PENDING/STATIC/DYNAMIC
STATUS_ORDER = ('STATIC', 'DYNAMIC', 'PENDING')
NEES_PANELS = ('moving', 'moving_first_seen_at_birth', 'static', 'static_classification_runs')


# --- files ----------------------------------------------------------------------------------


# --- printed summary ------------------------------------------------------------------------


def summary_text(content: Mapping[str, Any]) -> str:
    """Return the printed summary of a report (``evaluate.report``)."""
    config, classification = content['config'], content['classification']
    totals = classification['totals']
    rates, window = totals['rates'], config['window_frames']
    scene = config['classification_scene']
    lines = [
        f'Shadow filter on seeds {_seed_text(config["seeds"])}: {scene["duration_s"]:g} s at '
        f'{scene["rate_hz"]:g} Hz, focal {scene["focal_px"]:g} px, '
        f'{scene["pixel_noise_px"]:g} px noise{_offsets(scene)}, true poses, alpha '
        f'{config["alpha"]:g}, '
        f'unchecked directions {config["shadow"]["classifier"]["unchecked_directions"]}, '
        f'static test {config["shadow"]["classifier"]["static_test"]}',
        f'classification, {totals["tracks"]} tracks (truth x final status):',
        f'  {"":8s}' + ''.join(f'{name:>9s}' for name in STATUS_ORDER),
    ]
    for truth, row in totals['confusion'].items():
        lines.append(f'  {truth:8s}' + ''.join(f'{row.get(n, 0):9d}' for n in STATUS_ORDER))
    lines.append(
        f'  static called DYNAMIC: {rates["static_called_dynamic"]} = '
        f'{_percent(rates["static_called_dynamic_of_decided"])} of decided, '
        f'{_percent(rates["static_called_dynamic_of_all"])} of all; '
        f'moving called STATIC: {rates["moving_called_static"]}'
    )
    sweep = ', '.join(
        f'{entry["alpha"]:g}: {_percent(entry["rates"]["static_called_dynamic_of_decided"])} '
        f'({entry["rates"]["moving_called_static"]} moving->STATIC)'
        for entry in classification['alpha_sweep']
    )
    lines.append(f'  alpha sweep, static called DYNAMIC of decided: {sweep}')
    if (unfit := totals.get('dynamic_without_fit')) is not None:
        lines.append(
            f'  called DYNAMIC because their views fix no static point (evidence of motion): '
            f'static {unfit["static"]}, moving {unfit["moving"]}'
        )
    for group in ('all_features', 'parallax_allows'):
        latency = totals['latency']['all'][group]
        lines.append(
            f'  frames to decide, {group.replace("_", " ")} ({latency["features"]} tracks, '
            f'{latency["decided"]} decided): median {_number(latency["median_frames"])}, p90 '
            f'{_number(latency["p90_frames"])}; within {window}: '
            f'{_percent(latency["within_window_of_decided"])} of decided, '
            f'{_percent(latency["within_window_of_all"])} of all'
        )
    seeds = _seed_text(config['consistency_seeds'])
    lines.append(
        f'consistency: tracker only on model motion (seeds {seeds}); handovers and '
        'static_classification_runs from the classification runs:'
    )
    for name, entry in content['consistency']['totals'].items():
        sigma, tracks = entry['within_3sigma'], entry['nees_track_means']
        low, high = tracks['ci95']
        lines.append(
            f'  {name}: {entry["samples"]} samples of {entry["tracks"]} tracks; NEES mean '
            f'{_number(entry["nees_mean"], 2)}, median {_number(entry["nees_median"], 2)} '
            f'(expected 3, 2.37); per-track mean {_number(tracks["mean"], 2)}, 95 % interval '
            f'[{_number(low, 2)}, {_number(high, 2)}]; above chi2 95 %: '
            f'{_percent(entry["fraction_nees_above_chi2_95"])}; within 3 sigma x/y/z '
            f'{_percent(sigma["x"])}/{_percent(sigma["y"])}/{_percent(sigma["z"])}; '
            f'ages in 95 % band: {_percent(entry["by_age"]["fraction_of_ages_inside_band_95"])}'
        )
    for failure in content.get('failures', []):
        lines.append(
            f'FAILED {failure["runs"]} run, alpha {failure["alpha"]:g}: {failure["error"]}'
        )
    runtime = content['runtime']
    lines.append(
        f'runtime {runtime["wall_s"]:.1f} s; filter {runtime["filter_ms_per_frame"]:.2f} '
        f'ms/frame over {runtime["frames"]} frames'
    )
    return '\n'.join(lines)


def _percent(value: float | None) -> str:
    return '-' if value is None or not math.isfinite(value) else f'{100 * value:.1f} %'


def _number(value: float | None, digits: int = 0) -> str:
    return '-' if value is None or not math.isfinite(value) else f'{value:.{digits}f}'


def _seed_text(seeds: Sequence[int]) -> str:
    if len(seeds) > 2 and list(seeds) == list(range(seeds[0], seeds[-1] + 1)):
        return f'{seeds[0]}-{seeds[-1]}'
    return ','.join(str(seed) for seed in seeds)


# --- figures --------------------------------------------------------------------------------


def write_figures(directory: Path, inputs: Mapping[str, Any]) -> list[Path]:
    """Draw every figure whose inputs are present into ``directory``; return the paths."""
    import matplotlib

    matplotlib.use('Agg')
    drawings: list[tuple[str, Callable[[Any, Any], None], Any, tuple[float, float]]] = [
        ('shadow_classification.png', _classification, inputs, (7.5, 4.0)),
        ('shadow_alpha_sweep.png', _alpha_sweep, inputs['alpha_sweep'], (6.0, 4.0)),
        ('shadow_decision_time.png', _decision_time, inputs['decisions'], (15.0, 4.2)),
    ]
    if inputs.get('timeline'):
        drawings.append(('shadow_timeline.png', _timeline, inputs['timeline'], (8.0, 4.0)))
        drawings.append(('shadow_snapshot.png', _snapshot, inputs['timeline'], (7.0, 5.6)))
    if inputs.get('feature'):
        drawings.append(('shadow_fig2_trajectory.png', _trajectory, inputs['feature'], (11, 4.5)))
        drawings.append(('shadow_fig3_errors.png', _errors, inputs['feature'], (8.0, 7.0)))
    curves = {
        k: v for k, v in inputs['nees_curves'].items() if k in NEES_PANELS and v['mean_nees']
    }
    if curves:
        rows = (len(curves) + 1) // 2
        drawings.append(('shadow_nees.png', _nees, curves, (10.0, 4.0 * rows)))
    return [
        write_atomically(directory / name, render_png(draw, data, size))
        for name, draw, data, size in drawings
    ]


def _classification(figure: Any, inputs: Mapping[str, Any]) -> None:
    by_motion = inputs['confusion_by_motion']
    rows = ['static', *sorted(k for k in by_motion if k != 'static')]
    table = np.array([[by_motion.get(r, {}).get(n, 0) for n in STATUS_ORDER] for r in rows])
    moving = inputs['confusion'].get('moving', {})
    rows.append('moving (all)')
    table = np.vstack([table, [moving.get(n, 0) for n in STATUS_ORDER]]).astype(float)
    shares = table / np.maximum(table.sum(axis=1, keepdims=True), 1.0)
    axes = figure.add_subplot()
    axes.imshow(shares, cmap='Blues', vmin=0.0, vmax=1.0, aspect='auto')
    for (row, column), count in np.ndenumerate(table):
        colour = 'white' if shares[row, column] > 0.6 else 'black'
        axes.text(
            column,
            row,
            f'{count:.0f}\n{100 * shares[row, column]:.1f} %',
            ha='center',
            va='center',
            fontsize=8,
            color=colour,
        )
    axes.set_xticks(range(len(STATUS_ORDER)), STATUS_ORDER)
    axes.set_yticks(range(len(rows)), rows)
    axes.set_xlabel('final status')
    axes.set_ylabel('truth (motion kind)')
    axes.set_title('classification over all seeds (row shares)')


def _alpha_sweep(figure: Any, sweep: Sequence[Mapping[str, Any]]) -> None:
    axes = figure.add_subplot()
    alphas = np.array([entry['alpha'] for entry in sweep])
    for key, label in (
        ('static_called_dynamic_of_decided', 'of decided static'),
        ('static_called_dynamic_of_all', 'of all static'),
    ):
        values = [_finite(entry['rates'][key]) for entry in sweep]
        axes.plot(alphas, values, 'o-', label=f'static called DYNAMIC, {label}')
    axes.plot(alphas, alphas, 'k--', lw=0.8, label='alpha')
    for alpha, entry in zip(alphas, sweep, strict=True):
        axes.annotate(
            f'{entry["rates"]["moving_called_static"]} moving\n->STATIC',
            (alpha, 0),
            textcoords='offset points',
            xytext=(0, 6),
            ha='center',
            fontsize=7,
        )
    axes.set_xlabel('alpha')
    axes.set_ylabel('rate')
    axes.set_ylim(bottom=0.0)
    axes.legend(fontsize=8)
    axes.grid(True, lw=0.3)
    axes.set_title('static features called DYNAMIC against alpha')


def _finite(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _decision_time(figure: Any, data: Mapping[str, Any]) -> None:
    scatter, binned, cdf = figure.subplots(1, 3)
    frames, status, moving = data['frames_to_decide'], data['status'], data['moving']
    window = data['window_frames']
    decided = frames >= 0
    for truth, code, colour, marker, label in (
        (False, STATUS_CODES['STATIC'], 'tab:blue', 'o', 'static -> STATIC'),
        (False, STATUS_CODES['DYNAMIC'], 'tab:orange', 'o', 'static -> DYNAMIC'),
        (True, STATUS_CODES['DYNAMIC'], 'tab:green', 's', 'moving -> DYNAMIC'),
        (True, STATUS_CODES['STATIC'], 'tab:red', 'x', 'moving -> STATIC'),
    ):
        keep = decided & (moving == truth) & (status == code)
        scatter.scatter(
            data['decision_parallax_deg'][keep],
            frames[keep],
            s=8,
            c=colour,
            marker=marker,
            alpha=0.6,
            label=f'{label} ({keep.sum()})',
        )
    scatter.axvline(data['min_parallax_deg'], color='k', ls=':', lw=0.8)
    scatter.axhline(window, color='k', ls='--', lw=0.8)
    scatter.set_xlabel('parallax of the deciding test [deg]')
    scatter.set_ylabel('frames from first sight to decision')
    scatter.legend(fontsize=7)
    scatter.set_title('time to decide against parallax')
    edges = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 20.0, 90.0])
    centres = np.sqrt(np.maximum(edges[:-1], 0.25) * edges[1:])
    parallax = data['window_parallax_deg']
    for truth, colour, label in ((False, 'tab:blue', 'static'), (True, 'tab:green', 'moving')):
        mine = np.isfinite(parallax) & (moving == truth)
        bins = np.digitize(parallax[mine], edges) - 1
        quick = decided[mine] & (frames[mine] <= window)
        shares = [quick[bins == b].mean() if np.any(bins == b) else np.nan for b in range(11)]
        binned.plot(centres, shares, 'o-', color=colour, label=f'{label} ({mine.sum()})')
    binned.axvline(data['min_parallax_deg'], color='k', ls=':', lw=0.8, label='min parallax')
    binned.set_xscale('log')
    binned.set_xlabel(f'true parallax after {window} frames [deg]')
    binned.set_ylabel(f'share decided within {window} frames')
    binned.set_ylim(-0.02, 1.02)
    binned.legend(fontsize=7)
    binned.set_title('tracks seen for the whole window')
    allows = np.isfinite(parallax) & (parallax >= data['min_parallax_deg'])
    for keep, label in ((np.ones_like(decided), 'all tracks'), (allows, 'parallax allows')):
        steps = np.sort(frames[keep & decided])
        share = np.arange(1, len(steps) + 1) / max(int(keep.sum()), 1)
        cdf.step(steps, share, where='post', label=f'{label} ({keep.sum()})')
    cdf.axvline(window, color='k', ls='--', lw=0.8)
    cdf.set_xlabel('frames from first sight to decision')
    cdf.set_ylabel('share of tracks decided')
    cdf.set_ylim(0.0, 1.0)
    cdf.legend(fontsize=7)
    cdf.set_title('decided by frame n (undecided never)')
    for axes in (scatter, binned, cdf):
        axes.grid(True, lw=0.3)


def _timeline(figure: Any, data: Mapping[str, Any]) -> None:
    axes = figure.add_subplot()
    counts = data['counts']
    times = np.arange(len(counts)) / data['rate_hz']
    axes.stackplot(
        times,
        counts[:, 0],
        counts[:, 1],
        counts[:, 2],
        colors=[STATUS_COLOURS[n] for n in ('PENDING', 'STATIC', 'DYNAMIC')],
        labels=['PENDING', 'STATIC', 'DYNAMIC'],
        alpha=0.7,
    )
    axes.plot(times, data['moving_visible'], 'k-', lw=1.0, label='truly moving, visible')
    axes.axvline(data['snapshot_frame'] / data['rate_hz'], color='k', ls=':', lw=0.8)
    axes.set_xlabel('time [s]')
    axes.set_ylabel('visible features')
    axes.legend(fontsize=8, loc='upper right')
    axes.set_title(f'status of the visible features, seed {data["seed"]} (dotted: snapshot)')


def _snapshot(figure: Any, data: Mapping[str, Any]) -> None:
    axes = figure.add_subplot()
    pixels, statuses, moving = data['pixels'], data['statuses'], data['moving']
    for name, code in STATUS_CODES.items():
        for truth, marker in ((False, 'o'), (True, '^')):
            keep = (statuses == code) & (moving == truth)
            if keep.any():
                axes.scatter(
                    pixels[keep, 0],
                    pixels[keep, 1],
                    c=STATUS_COLOURS[name],
                    marker=marker,
                    s=30,
                    edgecolors='k',
                    linewidths=0.4,
                    label=f'{name}, truly {"moving" if truth else "static"}',
                )
    width, height = data['image_size']
    axes.set_xlim(0, width)
    axes.set_ylim(height, 0)
    axes.set_aspect('equal')
    axes.set_xlabel('u [px]')
    axes.set_ylabel('v [px]')
    axes.legend(fontsize=7, loc='lower right')
    axes.set_title(
        f'seed {data["seed"]}, frame {data["snapshot_frame"]}: pending red, '
        'static blue, dynamic green'
    )


def _trajectory(figure: Any, data: Mapping[str, Any]) -> None:
    for index, (first, second, name) in enumerate(((0, 1, 'XY'), (0, 2, 'XZ'))):
        axes = figure.add_subplot(1, 2, index + 1)
        axes.plot(
            data['camera_path'][:, first],
            data['camera_path'][:, second],
            '-',
            color='tab:green',
            lw=1.0,
            label='camera',
        )
        axes.plot(
            data['true_path'][:, first],
            data['true_path'][:, second],
            '-',
            color='tab:red',
            lw=1.2,
            label='feature (truth)',
        )
        axes.plot(
            data['estimates'][:, first],
            data['estimates'][:, second],
            '.',
            color='tab:blue',
            ms=2,
            label='Shadow filter estimate',
        )
        axes.set_xlabel('xyz'[first] + ' [m]')
        axes.set_ylabel('xyz'[second] + ' [m]')
        axes.set_aspect('equal', adjustable='datalim')
        axes.grid(True, lw=0.3)
        axes.set_title(f'{name} (seed {data["seed"]}, track {data["track_id"]})')
        axes.legend(fontsize=7)


def _errors(figure: Any, data: Mapping[str, Any]) -> None:
    grid = figure.subplots(3, 1, sharex=True)
    ages = data['ages']
    for axis, axes in enumerate(grid):
        bound = 3.0 * data['sigmas'][:, axis]
        axes.plot(ages, data['errors'][:, axis], '-', color='tab:green', lw=1.0, label='error')
        axes.plot(ages, bound, '-', color='tab:red', lw=0.8, label='+-3 sigma')
        axes.plot(ages, -bound, '-', color='tab:red', lw=0.8)
        limit = 1.5 * float(
            np.percentile(np.abs(np.concatenate([bound, data['errors'][:, axis]])), 95)
        )
        axes.set_ylim(-limit, limit)
        axes.set_ylabel(f'{"xyz"[axis]} error [m]')
        axes.grid(True, lw=0.3)
    grid[0].legend(fontsize=8)
    grid[0].set_title(
        f'seed {data["seed"]}, track {data["track_id"]} (final {data["status"]}): '
        'errors while the depth is defined'
    )
    grid[-1].set_xlabel('frames since first sight')


def _nees(figure: Any, curves: Mapping[str, Mapping[str, Sequence[float]]]) -> None:
    columns = min(len(curves), 2)
    rows = (len(curves) + 1) // 2
    grid = np.atleast_1d(figure.subplots(rows, columns, sharey=True, squeeze=False)).ravel()
    for axes in grid[len(curves) :]:
        axes.set_visible(False)
    for axes, (name, curve) in zip(grid, curves.items(), strict=False):
        ages = np.array(curve['age_frames'])
        axes.fill_between(
            ages,
            curve['band_low'],
            curve['band_high'],
            color='tab:red',
            alpha=0.25,
            step='mid',
            label='95 % band of the average',
        )
        axes.plot(ages, curve['mean_nees'], '-', color='tab:blue', lw=1.0, label='average NEES')
        axes.axhline(3.0, color='k', ls='--', lw=0.8)
        axes.set_yscale('log')
        axes.set_xlabel('frames since first sight')
        axes.grid(True, lw=0.3)
        axes.set_title(name.replace('_', ' '), fontsize=9)
        counts = axes.twinx()
        counts.plot(ages, curve['samples'], ':', color='grey', lw=0.8)
        counts.set_ylabel('samples averaged', color='grey', fontsize=8)
        counts.set_ylim(bottom=0)
        axes.set_ylabel('average NEES (3 dof)')
    grid[0].legend(fontsize=7)


def _offsets(scene: Mapping[str, Any]) -> str:
    """' + offsets ...' when the scene's tracking noise is not white, else ''."""
    if not scene.get('tracking_offset_px'):
        return ''
    return (
        f' + tracking offsets {scene["tracking_offset_px"]:g} px (tau '
        f'{scene["tracking_offset_time_s"]:g} s, jumps {scene["tracking_jump_probability"]:g}'
        '/frame)'
    )
