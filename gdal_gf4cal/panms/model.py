"""The pan-MS registration model (METHODS §9): :class:`PanMSModel` (``predict``, JSON round trip), its
constants and :class:`PanMSError`."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ..basis import trigonometric
from ..errors import Gf4calError
from ..outputs import atomic_output, check_output_path

AXES = ("sample", "line")
ORDER = 4
#: Nominal GF7 backward-camera MS line period (s), instantaneous field of view (rad) and pan-MS look-time
#: difference (s) (METHODS §9, §10): only used to express jitter in Hz and as attitude angles.
GF7_MS_LINE_TIME_S = 3.65e-4
GF7_MS_IFOV_RAD = 5.105e-6
GF7_LOOK_TIME_S = 0.117
#: Threshold of the P(<= t) statistic (MS px, METHODS §9).
P_THRESHOLD_PX = 0.25


class PanMSError(Gf4calError, ValueError):
    """Pan-MS registration cannot be done with these inputs (the message says what to do)."""



@dataclass
class PanMSModel:
    """METHODS §9's registration model of one MS image against its pan (all in MS pixels, GDAL convention).

    ``linear`` = ``A1..A6`` of ``A1 + A2 s + A3 l`` (sample), ``A4 + A5 s + A6 l`` (line) with ``s, l``
    normalised to [-1, 1] over the MS image; ``piecewise[k, axis, j]`` the quartic coefficient of ``u_k^j`` in
    sub-CCD ``k`` (``u_k`` in [-1, 1] over the piece between ``breaks``); ``jitter[axis]`` =
    ``{"b": B, "components": [{"frequency_cycles_per_line", "sin", "cos", ...}]}`` for
    ``(1 + B s) sum_i (sin_i sin(2 pi f_i l) + cos_i cos(2 pi f_i l))`` with ``l`` in MS lines.
    """

    ms_size: Tuple[int, int]
    breaks: Tuple[float, ...]
    linear: np.ndarray = field(default_factory=lambda: np.zeros(6))
    piecewise: Optional[np.ndarray] = None
    jitter: Dict[str, dict] = field(default_factory=dict)
    steps: List[dict] = field(default_factory=list)
    mode: str = "solve"
    info: Dict[str, object] = field(default_factory=dict)
    #: Per cell of the estimate: flagged as a blunder by the last robust step (not serialised).
    cell_outlier: Optional[np.ndarray] = field(default=None, repr=False)
    #: The model after each step (``step_residuals`` evaluates the cells on them; not serialised).
    snapshots: List[dict] = field(default_factory=list, repr=False)

    def __post_init__(self):
        self.ms_size = (int(self.ms_size[0]), int(self.ms_size[1]))
        self.breaks = tuple(sorted(float(b) for b in self.breaks))
        self.linear = np.asarray(self.linear, dtype=float).reshape(6)
        if self.piecewise is None:
            self.piecewise = np.zeros((self.n_sub_ccds, 2, ORDER + 1))
        self.piecewise = np.asarray(self.piecewise, dtype=float).reshape(self.n_sub_ccds, 2, ORDER + 1)
        for ax in AXES:
            self.jitter.setdefault(ax, {"b": 0.0, "components": []})

    @property
    def n_sub_ccds(self) -> int:
        return len(self.breaks) + 1

    # -- evaluation -------------------------------------------------------------------------------------
    def normalise(self, sample, line):
        W, H = self.ms_size
        return (np.asarray(sample, float) - W / 2.0) / (W / 2.0), (np.asarray(line, float) - H / 2.0) / (H / 2.0)

    def predict(self, sample, line, *, terms: Sequence[str] = ("linear", "piecewise", "jitter")):
        """``(d_sample, d_line)`` of the model at MS image points (GDAL convention), MS pixels (METHODS §9)."""
        s, l = np.broadcast_arrays(np.asarray(sample, dtype=float), np.asarray(line, dtype=float))
        sn, ln = self.normalise(s, l)
        out = [np.zeros(s.shape), np.zeros(s.shape)]
        if "linear" in terms:
            a = self.linear
            out[0] = out[0] + a[0] + a[1] * sn + a[2] * ln
            out[1] = out[1] + a[3] + a[4] * sn + a[5] * ln
        if "piecewise" in terms:
            # = piecewise_polynomial(s, breaks, 4, domain=(0, W)) @ coefficients, by Horner per point (the
            # appliers evaluate it at every MS pixel)
            ends = np.concatenate([[0.0], self.breaks, [float(self.ms_size[0])]])
            mid, half = 0.5 * (ends[1:] + ends[:-1]), 0.5 * (ends[1:] - ends[:-1])
            j = np.searchsorted(np.asarray(self.breaks), s, side="right")
            one = j.size > 0 and int(j.min()) == int(j.max())          # one piece (most tiles): scalars
            jj = int(j.flat[0]) if one else j
            u = (s - mid[jj]) / half[jj]
            for k in range(2):
                coef = self.piecewise[:, k, :]
                v = np.full(u.shape, coef[jj, ORDER]) if one else np.take(coef[:, ORDER], j)
                for p in range(ORDER - 1, -1, -1):
                    v *= u
                    v += coef[jj, p] if one else np.take(coef[:, p], j)
                out[k] = out[k] + v
        if "jitter" in terms:
            for k, ax in enumerate(AXES):
                comps = self.jitter[ax]["components"]
                if comps:
                    out[k] = out[k] + self._jitter_series(ax, l) * (1.0 + self.jitter[ax]["b"] * sn)
        return out[0], out[1]

    def _jitter_series(self, ax: str, l):
        """``sum_i (sin_i sin(2 pi f_i l) + cos_i cos(2 pi f_i l))`` (basis.trigonometric). Many points: from a
        table every MS line, linearly interpolated (the jitter is < 0.01 cycle per line: error < 1e-6 px)."""
        comps = self.jitter[ax]["components"]
        f = [c["frequency_cycles_per_line"] for c in comps]
        coef = np.ravel([(c["sin"], c["cos"]) for c in comps])
        if l.size < 20000 or not np.all(np.isfinite(l)) or max(f) > 0.02:
            return trigonometric(l, f) @ coef
        lo, hi = math.floor(float(l.min())) - 1, math.ceil(float(l.max())) + 2
        if hi - lo > l.size:
            return trigonometric(l, f) @ coef
        grid = np.arange(lo, hi, dtype=float)
        return np.interp(l, grid, trigonometric(grid, f) @ coef)

    def compatible_with(self, ms_size, breaks=None) -> None:
        """Refuse reuse on another camera: another MS width or sub-CCD layout (METHODS §9 reuse mode)."""
        if int(ms_size[0]) != self.ms_size[0]:
            raise PanMSError(f"the reuse model is for an MS image {self.ms_size[0]} px wide but this MS image is "
                             f"{int(ms_size[0])} px wide: reuse only a model of the same camera and product")
        if breaks is not None and (len(breaks) != len(self.breaks)
                                   or not np.allclose(sorted(breaks), self.breaks, atol=0.5)):
            raise PanMSError(f"the reuse model has sub-CCD edges {list(self.breaks)} but {list(breaks)} were "
                             "asked: reuse only a model of the same camera (drop --sub-ccds/--breaks)")

    # -- serialisation ------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"model": "gf4cal-panms", "version": 1, "mode": self.mode, "ms_size": list(self.ms_size),
                "n_sub_ccds": self.n_sub_ccds, "breaks_ms_px": list(self.breaks),
                "linear": dict(zip(["A1", "A2", "A3", "A4", "A5", "A6"], self.linear.tolist())),
                "piecewise": self.piecewise.tolist(), "jitter": self.jitter, "steps": self.steps,
                "info": self.info, "pixel_convention": "gdal",
                "definition": "delta = MS image point - (pan point -> pan RPC on the DEM -> MS RPC), MS px "
                              "(METHODS §9); s_n = (s - W/2)/(W/2), l_n = (l - H/2)/(H/2); linear: sample A1 + "
                              "A2 s_n + A3 l_n, line A4 + A5 s_n + A6 l_n; piecewise[k][axis][j] u_k^j, u_k = "
                              "(s - mid_k)/half_k over sub-CCD k between 0, breaks, W; jitter[axis]: (1 + b s_n) "
                              "sum (sin sin(2 pi f l) + cos cos(2 pi f l)), l in MS lines"}

    @classmethod
    def from_dict(cls, d: dict) -> "PanMSModel":
        if d.get("model") != "gf4cal-panms":
            raise PanMSError("not a pan-MS registration model (model.json of gf4cal register-pan-ms expected)")
        lin = d["linear"]
        return cls(ms_size=tuple(d["ms_size"]), breaks=tuple(d["breaks_ms_px"]),
                   linear=[lin[k] for k in ("A1", "A2", "A3", "A4", "A5", "A6")],
                   piecewise=np.asarray(d["piecewise"], float), jitter=d.get("jitter", {}),
                   steps=d.get("steps", []), mode=d.get("mode", "solve"), info=d.get("info", {}))

    def to_json(self, path, overwrite: bool = False) -> str:
        """Write the model file atomically (temporary file in the same folder, then ``os.replace``), as
        :meth:`~gdal_gf4cal.camera.LookAngleModel.to_json`.

        Raises :class:`~gdal_gf4cal.errors.InputOverwriteError` if ``path`` exists and ``overwrite`` is false.
        """
        path = check_output_path(path, overwrite=overwrite)
        with atomic_output(path) as tmp, open(tmp, "w") as fh:
            json.dump(self.to_dict(), fh, indent=1, default=_json_default)
        return path

    @classmethod
    def from_json(cls, path) -> "PanMSModel":
        try:
            with open(os.fspath(path)) as fh:
                d = json.load(fh)
        except (OSError, ValueError) as exc:
            raise PanMSError(f"cannot read the reuse model {path}: {exc}") from None
        return cls.from_dict(d)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))
