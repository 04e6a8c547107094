"""Dense displacement of a random-dot frame against its reference: OpenCV's
DIS optical flow, the start of image matching on dots (full grid).

Image matching (:func:`processing.dic.refine_height`) needs a start inside
its basin; what it gives does not depend on where the start came from as
long as it is there.  OpenPIV's five window passes were that start and cost
almost all of a dots frame (0.6-0.9 s at 512^2, 2 cores).  DIS (Kroeger et
al. 2016: inverse-search patches of 8 px every 3 px on an image pyramid, down
to the finest scale, then a variational refinement) gives a dense flow in
0.11 s at 512^2.  Measured on the accuracy table's dot surfaces (ray-traced,
8 bit, noise 1 DN, docs/processing.md section 11), relative RMS height error
of the full grid after image matching, PIV start / DIS start, 256^2:
bump 4 um 0.12 / 0.12 %, bump 2 um sigma 4 mm 0.23 / 0.25, narrow bump 1.79 /
0.52, waves 12-30 mm 0.25 / 0.26, deep dimple 0.30 / 0.30, waves 6-12 mm
1.57 / 1.21; 512^2: 0.15 / 0.17, 0.39 / 0.42, 2.02 / 0.96, 0.34 / 0.36,
0.17 / 0.18, 1.61 / 1.18, at 129-176 ms a frame against 700-929 ms.  DIS
stopped one scale above the pixels (its "medium" preset) was 1.4-2.7x worse
after image matching on the narrow features; a smoothed flow worse too
(the flow is sampled, not averaged).

The flow is sampled on the PIV grid the dots chain solves on (so the
height solve, pin and image matching's start are the PIV path's own), and
each sample is checked the way PIV's correlation peak is: the reference
warped by the flow must correlate with the frame over the window around the
sample (zero-normalised, :data:`MIN_ZNCC`); elsewhere (lost TIR, a blank or
saturated part, a flow that went astray) the sample is invalid.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["DenseDotFlow", "MIN_ZNCC", "to_8bit"]

#: Least zero-normalised correlation, over a window around a sample, of the
#: frame and the reference warped by the flow, for the sample to count (PIV's
#: correlation peaks on good dots: 0.9 and more; on noise about 0).
MIN_ZNCC = 0.5


def to_8bit(image, lo: float, hi: float) -> np.ndarray:
    """``image`` mapped linearly from ``[lo, hi]`` to 0-255, clipped, uint8 (DIS reads 8 bits)."""
    scale = 255.0 / max(float(hi) - float(lo), 1e-12)
    out = (np.asarray(image, np.float32) - np.float32(lo)) * np.float32(scale)
    return np.clip(out, 0.0, 255.0, out=out).astype(np.uint8)


class DenseDotFlow:
    """DIS optical flow of frames against one random-dot reference, sampled on a grid.

    Parameters
    ----------
    reference : ndarray (rows, cols)
        The dot pattern seen via the flat surface (any real dtype).
    rows_px, cols_px : ndarray
        Pixel coordinates of the grid the displacement is returned on.
    window_px : int
        Side of the window around each sample whose correlation validates it.
    max_displacement_px : float
        Largest displacement accepted, pixels.
    """

    def __init__(self, reference, rows_px, cols_px, *, window_px: int = 16, max_displacement_px: float = 30.0):
        ref = np.asarray(reference)
        # 8-bit range of the reference (frames are mapped the same way): its 0.1 and 99.9 percentiles
        lo, hi = np.percentile(ref[::2, ::2], [0.1, 99.9])
        self.range = (float(lo), float(hi) if hi > lo else float(lo) + 1.0)
        self.ref8 = to_8bit(ref, *self.range)
        sub = np.asarray(ref[::2, ::2], np.float32)
        self.ref_mean, self.ref_std = float(sub.mean()), float(sub.std())
        self.shape = ref.shape
        self.window_px = int(window_px)
        self.max_displacement_px = float(max_displacement_px)
        self.rows_px = np.asarray(rows_px, np.float64)
        self.cols_px = np.asarray(cols_px, np.float64)
        grid_r, grid_c = np.meshgrid(self.rows_px, self.cols_px, indexing="ij")
        self._grid = (grid_c.astype(np.float32), grid_r.astype(np.float32))  # remap's (x, y)
        self._dis = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_dis"] = None  # cv2's objects do not pickle; made again on first use
        return state

    def _flow(self):
        if self._dis is None:  # made on first use (and after unpickling)
            dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
            dis.setFinestScale(0)  # down to the pixels (the preset stops one scale above)
            self._dis = dis
        return self._dis

    def __call__(self, frame):
        """Displacement of ``frame`` against the reference (``I(r) = I0(r - u(r))``).

        Returns
        -------
        u : ndarray float32 (2, n_rows, n_cols)
            ``(u_row, u_col)`` in pixels at ``(rows_px, cols_px)``, NaN where invalid.
        valid : ndarray bool (n_rows, n_cols)
        """
        img = np.asarray(frame)
        if img.shape != self.shape:
            raise ValueError(f"frame shape {img.shape} differs from the reference's {self.shape}")
        # DIS compares patch intensities less their means: a frame darker than the reference is brought
        # to the reference's contrast first (its mean and standard deviation matched to the reference's)
        sub = np.asarray(img[::2, ::2], np.float32)
        mean, std = float(sub.mean()), float(sub.std())
        gain = self.ref_std / std if std > 0 else 1.0
        lo, hi = self.range
        img8 = to_8bit(img, mean + (lo - self.ref_mean) / gain, mean + (hi - self.ref_mean) / gain)
        # flow from the frame to the reference: frame(r) = reference(r + f(r)), so u(r) = -f(r) at r itself
        f = self._flow().calc(img8, self.ref8, None)
        gx, gy = self._grid
        u = -np.stack([cv2.remap(f[..., 1], gx, gy, cv2.INTER_LINEAR), cv2.remap(f[..., 0], gx, gy, cv2.INTER_LINEAR)])
        valid = self._correlates(img8, f) & (np.hypot(u[0], u[1]) <= self.max_displacement_px)
        u = u.astype(np.float32)
        u[:, ~valid] = np.nan
        return u, valid

    def _correlates(self, img8, f):
        """Grid samples whose window correlates (ZNCC >= :data:`MIN_ZNCC`) with the reference warped by ``f``."""
        rows, cols = self.shape
        px, py = np.meshgrid(np.arange(cols, dtype=np.float32), np.arange(rows, dtype=np.float32))
        warped = cv2.remap(self.ref8, px + f[..., 0], py + f[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        a = img8.astype(np.float32)
        box = (self.window_px, self.window_px)

        def mean(x):
            return cv2.blur(x, box, borderType=cv2.BORDER_REFLECT)

        ma, mw = mean(a), mean(warped)
        cov = mean(a * warped) - ma * mw
        var = (mean(a * a) - ma * ma) * (mean(warped * warped) - mw * mw)
        zncc = cov / np.sqrt(np.maximum(var, 1e-6))
        gx, gy = self._grid
        return cv2.remap(zncc, gx, gy, cv2.INTER_NEAREST) >= MIN_ZNCC
