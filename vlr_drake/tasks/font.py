"""A single-stroke font for A-Z (the handwriting task's target letters).

Each letter is a list of strokes; a stroke is a polyline (M, 2) in a box 0 <= x <= width,
0 <= y <= 1 (height 1, baseline y = 0). Curves are polylines through arc points.
:func:`letter_strokes` returns the strokes scaled to a height and resampled to a spacing.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LETTERS", "letter_strokes", "word_letters", "resample"]


def _arc(cx: float, cy: float, rx: float, ry: float, a0: float, a1: float, n: int = 9) -> list:
    t = np.deg2rad(np.linspace(a0, a1, n))
    return [(cx + rx * np.cos(a), cy + ry * np.sin(a)) for a in t]


#: Letter strokes in the unit-height box (width 0.7 unless narrower).
LETTERS: dict[str, list[list[tuple[float, float]]]] = {
    "A": [[(0, 0), (0.35, 1), (0.7, 0)], [(0.15, 0.42), (0.55, 0.42)]],
    "B": [
        [(0, 0), (0, 1), (0.45, 1)]
        + _arc(0.45, 0.76, 0.22, 0.24, 90, -90, 7)
        + [(0, 0.52), (0.48, 0.52)]
        + _arc(0.48, 0.26, 0.22, 0.26, 90, -90, 7)
        + [(0, 0)]
    ],
    "C": [_arc(0.4, 0.5, 0.38, 0.5, 45, 315, 15)],
    "D": [[(0, 0), (0, 1), (0.3, 1)] + _arc(0.3, 0.5, 0.4, 0.5, 90, -90, 11) + [(0, 0)]],
    "E": [[(0.65, 1), (0, 1), (0, 0), (0.65, 0)], [(0, 0.5), (0.5, 0.5)]],
    "F": [[(0.65, 1), (0, 1), (0, 0)], [(0, 0.5), (0.5, 0.5)]],
    "G": [_arc(0.4, 0.5, 0.38, 0.5, 45, 340, 15) + [(0.78, 0.45), (0.45, 0.45)]],
    "H": [[(0, 0), (0, 1)], [(0.7, 0), (0.7, 1)], [(0, 0.5), (0.7, 0.5)]],
    "I": [[(0.35, 0), (0.35, 1)], [(0.1, 1), (0.6, 1)], [(0.1, 0), (0.6, 0)]],
    "J": [[(0.7, 1), (0.7, 0.3)] + _arc(0.4, 0.3, 0.3, 0.3, 0, -180, 9)[1:]],
    "K": [[(0, 0), (0, 1)], [(0.7, 1), (0, 0.4)], [(0.22, 0.6), (0.7, 0)]],
    "L": [[(0, 1), (0, 0), (0.65, 0)]],
    "M": [[(0, 0), (0, 1), (0.4, 0.35), (0.8, 1), (0.8, 0)]],
    "N": [[(0, 0), (0, 1), (0.7, 0), (0.7, 1)]],
    "O": [_arc(0.4, 0.5, 0.4, 0.5, 90, 450, 19)],
    "P": [[(0, 0), (0, 1), (0.4, 1)] + _arc(0.4, 0.75, 0.25, 0.25, 90, -90, 9) + [(0, 0.5)]],
    "Q": [_arc(0.4, 0.5, 0.4, 0.5, 90, 450, 19), [(0.45, 0.25), (0.8, -0.05)]],
    "R": [
        [(0, 0), (0, 1), (0.4, 1)] + _arc(0.4, 0.75, 0.25, 0.25, 90, -90, 9) + [(0, 0.5)],
        [(0.3, 0.5), (0.7, 0)],
    ],
    "S": [_arc(0.35, 0.75, 0.32, 0.25, 20, 270, 9) + _arc(0.35, 0.25, 0.32, 0.25, 90, -160, 9)[1:]],
    "T": [[(0, 1), (0.7, 1)], [(0.35, 1), (0.35, 0)]],
    "U": [[(0, 1), (0, 0.35)] + _arc(0.35, 0.35, 0.35, 0.35, 180, 360, 9)[1:] + [(0.7, 1)]],
    "V": [[(0, 1), (0.35, 0), (0.7, 1)]],
    "W": [[(0, 1), (0.2, 0), (0.4, 0.7), (0.6, 0), (0.8, 1)]],
    "X": [[(0, 1), (0.7, 0)], [(0, 0), (0.7, 1)]],
    "Y": [[(0, 1), (0.35, 0.5), (0.7, 1)], [(0.35, 0.5), (0.35, 0)]],
    "Z": [[(0, 1), (0.7, 1), (0, 0), (0.7, 0)]],
}


def resample(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """Points along a polyline (M, 2) at most ``spacing`` apart, keeping every vertex once (a
    vertex repeated, as where an arc starts on a line's last point, had been a waypoint
    written and scored twice)."""
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"'spacing' must be a positive finite number [m], got {spacing}")
    polyline = np.asarray(polyline, float)
    out = [polyline[0]]
    for p, q in zip(polyline[:-1], polyline[1:], strict=True):
        d = np.linalg.norm(q - p)
        if d <= 1e-9 * spacing:  # the same point again
            continue
        n = max(1, int(np.ceil(d / spacing)))
        out.extend(p + (q - p) * (k / n) for k in range(1, n + 1))
    return np.array(out)


def letter_strokes(letter: str, height: float, spacing: float | None = None) -> list[np.ndarray]:
    """Strokes of ``letter`` scaled to ``height`` [m] (the font's unit cap height; Q's tail
    reaches 5% below the baseline, as a descender does), centred on (0, 0), each resampled
    to ``spacing`` [m] when given. Raises ValueError for a letter outside A-Z."""
    key = letter.upper()
    if key not in LETTERS:
        raise ValueError(f"letter '{letter}' is not in the stroke font (A-Z)")
    if not (np.isfinite(height) and height > 0):
        raise ValueError(f"'height' must be a positive finite number [m], got {height}")
    strokes = [np.asarray(s, float) for s in LETTERS[key]]
    allp = np.concatenate(strokes)
    center = 0.5 * (allp.min(axis=0) + allp.max(axis=0))
    strokes = [(s - center) * height for s in strokes]
    if spacing is not None:
        strokes = [resample(s, spacing) for s in strokes]
    return strokes


def word_letters(word: str) -> list[str]:
    """The letters of ``word`` (spaces dropped); ValueError names any character not in A-Z."""
    chars = [c for c in word if not c.isspace()]
    # (ASCII first: str.upper() takes the dotless i and the long s to I and S)
    bad = [c for c in chars if not (c.isascii() and c.upper() in LETTERS)]
    if not chars or bad:
        which = f": {''.join(sorted(set(bad)))!r} not in A-Z" if bad else ""
        raise ValueError(f"word must consist of letters A-Z, got '{word}'{which}")
    return [c.upper() for c in chars]
