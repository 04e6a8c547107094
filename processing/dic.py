"""Image-domain refinement of the displacement: global Gauss-Newton image matching (DIC).

Fourier demodulation sees the frame through a band around each carrier;
where the surface has features a few carrier periods wide the phase
modulation spills out of that band and FD's displacement comes out smoothed
(docs/processing.md, section 6).  :func:`refine_global` matches images
instead of phases: starting from FD's displacement ``u`` (pixels,
``I(r) = I0(r - u(r))``) it solves, on a grid of nodes every
:data:`NODE_PX` pixels,

    min_u  sum_r w(r) [I(r) - I0(r - u(r))]^2  +  lam |D2 u|^2

by Gauss-Newton (``w``: FD's valid mask on the pixels; ``D2``: second
differences of the total displacement, a weak penalty that costs a linear
field nothing).  The Reconstructor (``refine_method="image"``) then solves
the heights on the node grid with its masked height solver and pin, and
interpolates them to every pixel.

The reference is warped by linear interpolation of its cubic-spline
interpolation on a grid :data:`FINE` times finer (:func:`fine_reference`):
OpenCV's cubic remap biases image matching towards whole pixels by up to
0.035 px, which sank earlier versions of this refinement.

Measured (docs/processing.md, section 6): ray-traced waves 3-6 carrier
periods long 2.90 % -> 1.11 % rms height error (goal 1.0 %).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["NODE_PX", "NodeGrid", "fine_reference", "reference_gradients", "refine_global"]


def reference_gradients(reference):
    """``(dI0/drow, dI0/dcol)`` of the reference, float32 (central differences)."""
    ref = np.asarray(reference, np.float32)
    return (np.gradient(ref, axis=0).astype(np.float32), np.gradient(ref, axis=1).astype(np.float32))


#: Refinement of the grid the reference is interpolated from (see :func:`fine_reference`).
FINE = 2


def fine_reference(reference):
    """The reference, cubic-spline interpolated to a grid ``FINE`` times finer
    (sample ``i`` at pixel ``i / FINE``), float32.

    Warping it with linear interpolation is as accurate as warping the
    reference with the cubic spline itself, at OpenCV's speed: measured on a
    ray-traced 2 mm board shifted by 0.25-0.75 px, the shift found by image
    matching is off by 0.005 px (cv2 cubic on the reference: 0.035 px, cv2
    linear 0.009 px; the cubic kernel's error and the 1/32 px position
    quantisation of cv2.remap are what bias image matching towards whole
    pixels).
    """
    from scipy import ndimage

    ref = np.asarray(reference, np.float64)
    r = np.arange(FINE * ref.shape[0]) / FINE
    c = np.arange(FINE * ref.shape[1]) / FINE
    coef = ndimage.spline_filter(ref, order=3, mode="mirror")
    out = np.empty((r.size, c.size), np.float32)
    # rows in blocks: the coordinate arrays stay small
    step = max(1, 2_000_000 // max(c.size, 1))
    for i in range(0, r.size, step):
        rr, cc = np.meshgrid(r[i:i + step], c, indexing="ij")
        out[i:i + step] = ndimage.map_coordinates(coef, [rr, cc], order=3, prefilter=False, mode="mirror")
    return out


# ------------------------------------------------------------------ global Gauss-Newton
#: Node spacing of the global solve, pixels (frame sides must be multiples of it).
NODE_PX = 4


def _resize_T_axis0(y, m, s):
    """Exact transpose of cv2.resize(INTER_LINEAR) from ``m`` to ``m * s``
    samples along axis 0 (integer factor ``s``): pixels -> nodes."""
    t = (np.arange(s) + 0.5) / s - 0.5
    yb = y.reshape(m, s, -1)
    out = np.zeros((m, yb.shape[2]), np.float32)
    for a in range(s):
        ta = float(t[a])
        ya = yb[:, a, :]
        c_own = np.float32(1.0 - abs(ta))
        c_nb = np.float32(abs(ta))
        out += c_own * ya
        if ta < 0:
            out[:-1] += c_nb * ya[1:]
            out[0] += c_nb * ya[0]  # before the first node cv2 clamps to it
        else:
            out[1:] += c_nb * ya[:-1]
            out[-1] += c_nb * ya[-1]
    return out


class NodeGrid:
    """Nodes every ``s`` pixels at ``j * s + (s - 1) / 2`` (cv2.resize's
    pixel-centre convention), bilinear node -> pixel map ``P`` and its exact
    transpose."""

    def __init__(self, frame_shape, s: int = NODE_PX):
        rows, cols = frame_shape
        if rows % s or cols % s:
            raise ValueError(f"the image refinement needs frame sides that are multiples of {s} px; "
                             f"got {rows} x {cols}: crop the frames (region of interest) or use refine_method='fd'")
        self.s = s
        self.frame_shape = (rows, cols)
        self.shape = (rows // s, cols // s)
        self.rows_px = np.arange(self.shape[0]) * s + (s - 1) / 2.0
        self.cols_px = np.arange(self.shape[1]) * s + (s - 1) / 2.0

    def up(self, x, interpolation=cv2.INTER_LINEAR):
        rows, cols = self.frame_shape
        return cv2.resize(np.ascontiguousarray(x, np.float32), (cols, rows), interpolation=interpolation)

    def up_T(self, y):
        """Exact transpose of :meth:`up` (pixels -> nodes).  (A cv2 tent filter
        sampled at the nodes gives the same, 1.7x slower at 1024^2.)"""
        m_r, m_c = self.shape
        a = _resize_T_axis0(y, m_r, self.s)
        return _resize_T_axis0(np.ascontiguousarray(a.T), m_c, self.s).T

    def down(self, x):
        """Cell means (pixels -> nodes)."""
        return cv2.resize(np.ascontiguousarray(x, np.float32), (self.shape[1], self.shape[0]),
                          interpolation=cv2.INTER_AREA)


def _second_differences(x):
    """``D2r^T D2r x + D2c^T D2c x`` on the node grid (both components)."""
    out = np.zeros_like(x)
    for axis in (-2, -1):
        xs = np.moveaxis(x, axis, 0)
        o = np.moveaxis(out, axis, 0)
        if xs.shape[0] < 3:
            continue
        d2 = xs[:-2] - 2.0 * xs[1:-1] + xs[2:]
        o[:-2] += d2
        o[1:-1] -= 2.0 * d2
        o[2:] += d2
    return out


def refine_global(fine, reference_gradient, frame, u_px, valid_px, grid: NodeGrid, *, outer: int = 3,
                  cg_iterations: int = 6, regularisation: float = 0.1):
    """Global Gauss-Newton image matching on a node grid.

    Minimises ``sum_r w(r) [I(r) - I0(r - u(r))]^2 + lam |D2 u|^2`` over the
    displacement at the nodes of ``grid`` (``u(r)``: Lanczos interpolation
    of the nodes for the warp; bilinear ``P`` with its exact transpose for
    the Gauss-Newton normal equations ``(P^T N P + lam D2^T D2) du = ...``,
    solved by block-Jacobi preconditioned conjugate gradients).  ``D2``: second
    differences of the total displacement along rows and columns; ``lam`` is
    ``regularisation`` times the mean data weight per node.  A linear field
    costs nothing; it holds nodes whose cells see no pattern edge and damps
    noise at the node spacing (measured: 0.03 too weak, node noise; 1 too
    strong, the 6-12 mm waves flattened; 0.1-0.2 best).

    Parameters
    ----------
    fine : ndarray float32
        :func:`fine_reference` of the reference.
    reference_gradient : (ndarray, ndarray)
    frame : ndarray (rows, cols)
    u_px : ndarray (2, rows, cols)
        Starting displacement on every pixel (FD's, NaN-free).
    valid_px : ndarray bool (rows, cols)
        Pixels whose residual counts.
    grid : NodeGrid

    Returns
    -------
    u : ndarray float32 (2, n_rows, n_cols)
        Displacement at the nodes (pixels).
    valid : ndarray bool (n_rows, n_cols)
        Nodes whose cell is all valid.
    """
    img = np.asarray(frame, np.float32)
    rows, cols = grid.frame_shape
    g0r, g0c = reference_gradient

    w = np.asarray(valid_px, np.float32)
    free = grid.down(w) > 0.999
    u = np.stack([grid.down(np.nan_to_num(u_px[i])) for i in range(2)]).astype(np.float64)
    r_px = np.arange(rows, dtype=np.float32)[:, None]
    c_px = np.arange(cols, dtype=np.float32)[None, :]
    rel = cv2.INTER_LINEAR | cv2.WARP_RELATIVE_MAP
    for _ in range(outer):
        mr = grid.up(u[0], cv2.INTER_LANCZOS4)
        mc = grid.up(u[1], cv2.INTER_LANCZOS4)
        warped = cv2.remap(fine, (c_px - mc) * np.float32(FINE), (r_px - mr) * np.float32(FINE),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        np.negative(mr, out=mr)
        np.negative(mc, out=mc)
        gr = cv2.remap(g0r, mc, mr, rel, borderMode=cv2.BORDER_REFLECT) * w
        gc = cv2.remap(g0c, mc, mr, rel, borderMode=cv2.BORDER_REFLECT) * w
        e = img - warped
        nrr, nrc, ncc = gr * gr, gr * gc, gc * gc
        b = np.stack([grid.up_T(gr * e), grid.up_T(gc * e)]).astype(np.float64)
        drr, drc, dcc = (grid.down(x) * grid.s ** 2 for x in (nrr, nrc, ncc))
        lam = regularisation * 0.5 * float(np.mean(drr + dcc))
        prr = drr + 12.0 * lam
        pcc = dcc + 12.0 * lam
        det = prr * pcc - drc * drc

        def prec(r):
            return np.stack([(pcc * r[0] - drc * r[1]) / det, (prr * r[1] - drc * r[0]) / det]) * free

        def op(x):
            xr = grid.up(x[0])
            xc = grid.up(x[1])
            out = np.stack([grid.up_T(nrr * xr + nrc * xc), grid.up_T(nrc * xr + ncc * xc)])
            out += lam * _second_differences(x)
            return out * free

        rhs = (-b - lam * _second_differences(u)) * free
        x = np.zeros_like(u)
        r = rhs
        z = prec(r)
        p = z.copy()
        rz = float(np.vdot(r, z))
        r0 = float(np.sqrt(np.vdot(r, r)))
        for _k in range(cg_iterations):
            if r0 == 0.0:
                break
            q = op(p)
            pq = float(np.vdot(p, q))
            if pq <= 0.0:
                break
            a = rz / pq
            x += a * p
            r = r - a * q
            if float(np.sqrt(np.vdot(r, r))) < 1e-3 * r0:
                break
            z = prec(r)
            rz_new = float(np.vdot(r, z))
            p = z + (rz_new / rz) * p
            rz = rz_new
        u += x
    return u.astype(np.float32), free


# ------------------------------------------------------------------ height on the node grid
def _interp_matrix(n_px: int, m: int, s: int):
    """Sparse ``(n_px, m)`` matrix of cv2.resize(INTER_LINEAR) from ``m`` nodes to ``n_px = m s`` pixels."""
    import scipy.sparse as sp

    x = (np.arange(n_px) + 0.5) / s - 0.5
    i0 = np.floor(x).astype(int)
    fr = x - i0
    low = i0 < 0
    high = i0 >= m - 1
    i0[low] = 0
    fr[low] = 0.0
    i0[high] = m - 1
    fr[high] = 0.0
    i1 = np.minimum(i0 + 1, m - 1)
    rows = np.concatenate([np.arange(n_px), np.arange(n_px)])
    return sp.csr_matrix((np.concatenate([1.0 - fr, fr]), (rows, np.concatenate([i0, i1]))), shape=(n_px, m))


def _derivative_matrix(m: int, spacing: float):
    """Sparse ``(m, m)`` first derivative: fourth-order central inside, second-order at the ends."""
    import scipy.sparse as sp

    D = sp.lil_matrix((m, m))
    for i in range(m):
        if 2 <= i <= m - 3:
            D[i, i - 2], D[i, i - 1], D[i, i + 1], D[i, i + 2] = 1 / 12, -8 / 12, 8 / 12, -1 / 12
        elif 1 <= i <= m - 2:
            D[i, i - 1], D[i, i + 1] = -0.5, 0.5
        elif i == 0:
            D[0, 0], D[0, 1], D[0, 2] = -1.5, 2.0, -0.5
        else:
            D[i, i], D[i, i - 1], D[i, i - 2] = 1.5, -2.0, 0.5
    return (D / spacing).tocsr()


def _third_difference_matrix(m: int):
    import scipy.sparse as sp

    if m < 4:
        return sp.csr_matrix((0, m))
    return sp.diags([-1.0, 3.0, -3.0, 1.0], [0, 1, 2, 3], shape=(m - 3, m)).tocsr()


class HeightNodes:
    """The height on a :class:`NodeGrid` and the exact linear optics of the
    geometry (:meth:`Geometry.linear_response` at the nodes):
    ``u = a h + B grad_px h`` (pixels), ``grad_px`` fourth-order central
    differences of the nodes.  ``L`` maps the node heights (mm) to the
    displacement at the nodes, ``(u_row ..., u_col ...)``."""

    def __init__(self, geometry, grid: NodeGrid):
        import scipy.sparse as sp

        self.grid = grid
        m_r, m_c = grid.shape
        s = grid.s
        lr = geometry.linear_response(grid.rows_px[:, None], grid.cols_px[None, :], grid.frame_shape)
        a = lr.a.reshape(-1, 2)
        B = lr.B.reshape(-1, 2, 2)
        Dr = sp.kron(_derivative_matrix(m_r, s), sp.identity(m_c)).tocsr()
        Dc = sp.kron(sp.identity(m_r), _derivative_matrix(m_c, s)).tocsr()
        blocks = []
        for i in range(2):
            blocks.append(sp.diags(a[:, i]) + sp.diags(B[:, i, 0]) @ Dr + sp.diags(B[:, i, 1]) @ Dc)
        self.L = sp.vstack(blocks).tocsr()
        self.LT = self.L.T.tocsr()
        R3 = sp.kron(_third_difference_matrix(m_r), sp.identity(m_c))
        C3 = sp.kron(sp.identity(m_r), _third_difference_matrix(m_c))
        self.reg = (R3.T @ R3 + C3.T @ C3).tocsr()
        # pixels <-> nodes (bilinear, exactly cv2's) and the products the
        # node normal matrix is assembled from
        rows, cols = grid.frame_shape
        Pr = _interp_matrix(rows, m_r, s)
        Pc = _interp_matrix(cols, m_c, s)
        self.PrT = Pr.T.tocsr()
        self.PcT = Pc.T.tocsr()
        self._pair = {}
        for name, P, m in (("r", Pr, m_r), ("c", Pc, m_c)):
            Pd = P.T.multiply(P.T).tocsr()  # (m, n): P[p, i]^2
            Po = (P.T[:-1].multiply(P.T[1:])).tocsr()  # (m-1, n): P[p, i] P[p, i+1]
            self._pair[name] = (Pd, Po)
        # constant-coefficient symbols for the DCT preconditioner
        kr = np.pi * np.arange(m_r) / m_r
        kc = np.pi * np.arange(m_c) / m_c
        d1r = ((8 * np.sin(kr) - np.sin(2 * kr)) / 6 / s) ** 2
        d1c = ((8 * np.sin(kc) - np.sin(2 * kc)) / 6 / s) ** 2
        self._sym_grad = (d1r[:, None], d1c[None, :])
        self._sym_reg = (2 - 2 * np.cos(kr))[:, None] ** 3 + (2 - 2 * np.cos(kc))[None, :] ** 3
        Bc = lr.B.reshape(-1, 2, 2).mean(axis=0)
        self.B_mean = Bc

    def displacement(self, h):
        """``(2, m_r, m_c)`` displacement at the nodes of heights ``h`` (m_r, m_c)."""
        return (self.L @ h.ravel()).reshape(2, *self.grid.shape)

    def node_normal(self, n_px):
        """``P^T N P`` for a pixel weight ``n_px`` (rows, cols) as a sparse
        ``(m, m)`` matrix (9-point stencil)."""
        import scipy.sparse as sp

        Rd, Ro = self._pair["r"]
        Cd, Co = self._pair["c"]
        m_r, m_c = self.grid.shape
        X = {"d": np.asarray(Rd @ n_px), "o": np.asarray(Ro @ n_px)}
        A = {}
        for k in "do":
            for l, C in (("d", Cd), ("o", Co)):
                A[k + l] = np.asarray(C @ X[k].T).T
        m = m_r * m_c
        # the 9-point stencil as diagonals of the flat (row-major) node index
        d1 = np.zeros((m_r, m_c))
        d1[:, :-1] = A["do"]  # (i,j)-(i,j+1)
        dmm = np.zeros((m_r, m_c))
        dmm[:-1, 1:] = A["oo"]  # (i,j)-(i+1,j-1): rows i, i+1 and columns j-1, j
        dm = np.zeros((m_r, m_c))
        dm[:-1] = A["od"]  # (i,j)-(i+1,j)
        dm1 = np.zeros((m_r, m_c))
        dm1[:-1, :-1] = A["oo"]  # (i,j)-(i+1,j+1)
        data = np.zeros((9, m))
        data[0] = A["dd"].ravel()
        offs = [0]
        for k, (off, d) in enumerate(zip((1, m_c - 1, m_c, m_c + 1), (d1, dmm, dm, dm1))):
            d = d.ravel()
            data[1 + 2 * k, off:] = d[:m - off]  # dia stores a[i, i + off] in column i + off
            data[2 + 2 * k, :m - off] = d[:m - off]
            offs += [off, -off]
        return sp.dia_matrix((data, offs), shape=(m, m))

    def node_rhs(self, y_px):
        """``P^T y`` (m_r, m_c)."""
        return np.asarray(self.PcT @ np.asarray(self.PrT @ y_px).T).T


def refine_height(fine, reference_gradient, frame, h0, valid_px, nodes: HeightNodes, *, outer: int = 2,
                  cg_iterations: int = 40, regularisation: float = 0.03, verbose=False, prefilter=None, cg_tol=1e-4, blur=None,
                  reference=None, edge_weight=None):
    """Gauss-Newton image matching for the height on the node grid of ``nodes``:
    ``min_h sum_r w [I - I0(r - P L h)]^2 + lam (|D3r h|^2 + |D3c h|^2)``."""
    import scipy.sparse as sp
    import scipy.fft as sfft

    grid = nodes.grid
    img = np.asarray(frame, np.float32)
    if prefilter:
        img = cv2.GaussianBlur(img, (0, 0), prefilter)
        ref = cv2.GaussianBlur(np.asarray(reference, np.float32), (0, 0), prefilter)
        fine = fine_reference(ref)
        reference_gradient = reference_gradients(ref)
    if blur:
        img = cv2.GaussianBlur(img, (0, 0), blur)
    rows, cols = grid.frame_shape
    g0r, g0c = reference_gradient
    w = np.asarray(valid_px, np.float32)
    if edge_weight is not None:
        w = w * edge_weight(reference)
    free = grid.down(w) > 0.999
    h = np.nan_to_num(np.asarray(h0, np.float64)).copy()
    r_px = np.arange(rows, dtype=np.float32)[:, None]
    c_px = np.arange(cols, dtype=np.float32)[None, :]
    rel = cv2.INTER_LINEAR | cv2.WARP_RELATIVE_MAP
    m_r, m_c = grid.shape
    L, LT = nodes.L, nodes.LT
    for step in range(outer):
        u = nodes.displacement(h)
        mr = grid.up(u[0], cv2.INTER_LANCZOS4)
        mc = grid.up(u[1], cv2.INTER_LANCZOS4)
        warped = cv2.remap(fine, (c_px - mc) * np.float32(FINE), (r_px - mr) * np.float32(FINE),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        np.negative(mr, out=mr)
        np.negative(mc, out=mc)
        gr = cv2.remap(g0r, mc, mr, rel, borderMode=cv2.BORDER_REFLECT)
        gc = cv2.remap(g0c, mc, mr, rel, borderMode=cv2.BORDER_REFLECT)
        if blur:
            warped = cv2.GaussianBlur(warped, (0, 0), blur)
            gr = cv2.GaussianBlur(gr, (0, 0), blur)
            gc = cv2.GaussianBlur(gc, (0, 0), blur)
        gr *= w
        gc *= w
        e = img - warped
        Nrr = nodes.node_normal(gr * gr)
        Nrc = nodes.node_normal(gr * gc)
        Ncc = nodes.node_normal(gc * gc)
        b = np.concatenate([nodes.node_rhs(gr * e).ravel(), nodes.node_rhs(gc * e).ravel()])
        nr = float(np.mean(gr * gr)) * grid.s ** 2
        nc = float(np.mean(gc * gc)) * grid.s ** 2
        Bm = nodes.B_mean
        dsym = nr * Bm[0, 0] ** 2 * nodes._sym_grad[0] + nc * Bm[1, 1] ** 2 * nodes._sym_grad[1]
        dsym = dsym + nr * Bm[0, 1] ** 2 * nodes._sym_grad[1] + nc * Bm[1, 0] ** 2 * nodes._sym_grad[0]
        scale = nr * Bm[0, 0] ** 2 / grid.s ** 2 + nc * Bm[1, 1] ** 2 / grid.s ** 2
        lam = regularisation * scale
        sym = dsym + lam * nodes._sym_reg
        sym[0, 0] = np.inf
        n = m_r * m_c
        R = nodes.reg

        def apply_K(x):
            v = L @ x
            vr, vc = v[:n], v[n:]
            return LT @ np.concatenate([Nrr @ vr + Nrc @ vc, Nrc @ vr + Ncc @ vc]) + lam * (R @ x)

        rhs = -(LT @ b) - lam * (R @ h.ravel())

        def prec(r):
            c = sfft.dctn(r.reshape(m_r, m_c), type=2, norm="ortho")
            c /= sym
            return sfft.idctn(c, type=2, norm="ortho").ravel()

        x = np.zeros(m_r * m_c)
        r = rhs.copy()
        z = prec(r)
        p = z.copy()
        rz = float(r @ z)
        r0 = float(np.sqrt(r @ r))
        k = 0
        for k in range(cg_iterations):
            if r0 == 0.0:
                break
            q = apply_K(p)
            pq = float(p @ q)
            if pq <= 0.0:
                break
            al = rz / pq
            x += al * p
            r -= al * q
            if float(np.sqrt(r @ r)) < cg_tol * r0:
                break
            z = prec(r)
            rz_new = float(r @ z)
            p = z + (rz_new / rz) * p
            rz = rz_new
        if verbose:
            print(f"  step {step}: cg {k + 1}, res {float(np.sqrt(r @ r)) / max(r0, 1e-30):.1e}, "
                  f"|e| {float(np.sqrt(np.mean(e * e))):.3f}")
        h += x.reshape(m_r, m_c)
    return h, nodes.displacement(h).astype(np.float32), free
