"""The Gauss-Newton matrix of the refinement's energy in its fixed block sparsity pattern.

For the residuals of :class:`solver.refine.form_energy.FormEnergy` (``r = J`` of the free
coordinates, in groups of a fixed number of vertices per residual), ``J^T J`` has a 3x3 block
(``dim`` x ``dim``) between every two vertices that share a residual, and that pattern never
changes between iterations. :class:`GaussNewtonSystem` computes it once (where every product
of two gradient slots lands in the values of the upper-triangle CSR matrix that
:func:`solver.linalg.factorize` reads with ``triangle="upper"``), then assembles ``J^T J``
and ``J^T r`` at any positions with one ``bincount`` per group: no sparse matrix product, no
format conversion. Patterns are kept per process (:data:`PATTERN_CACHE_BYTES`), so a mesh
seen before skips the set-up.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp

from ..mesh.topology import MeshTopology
from .form_energy import FormEnergy
from .residual_groups import ResidualGroup, square_sum


@dataclass
class _GroupScatter:
    """Where a :class:`solver.refine.residual_groups.ResidualGroup`'s products land.

    ``local``: (rows, q) int32, each slot's free vertex (-1: fixed); the gradient entries
    and the diagonal blocks' entries ``(diag_r, diag_c)`` land where it says (computed at
    each assembly: cheap, and 320 B per face less kept). ``J^T J``'s off-diagonal blocks:
    the products ``G_k[r] G_l[c]`` of the slot pairs ``(pair_k, pair_l)``, k < l, land in the
    matrix's values in the block whose rank in its row ``rank`` (pairs, rows) int32 gives
    (:func:`_pair_destinations`). Entries of fixed vertices land
    one past the end (position ``n_free * dim`` of ``J^T r``, ``nnz`` of the values), a slot
    that is dropped: no index arrays of the kept ones. ``twice``: the diagonal entries of
    degenerate hinges (two slots on one vertex), as (flat product index, position).
    """

    local: np.ndarray | None = None
    diag_r: np.ndarray | None = None     # diagonal blocks: entries (r, c), r <= c
    diag_c: np.ndarray | None = None
    pair_k: np.ndarray | None = None     # off-diagonal blocks: slot pairs k < l
    pair_l: np.ndarray | None = None
    rank: np.ndarray | None = None
    twice: tuple[np.ndarray, np.ndarray] | None = None


KEPT_POSITIONS_BYTES = 32 * 2**20
"""A :class:`GaussNewtonSystem` whose positions of every gradient entry and product in
``J^T r`` and ``J^T J``'s off-diagonal values (int64, ~0.97 KB per face; the diagonal blocks
are summed per vertex) take at most this many bytes (meshes up to ~35K faces) keeps them
from its first assembly; a larger one computes them at
each assembly from its compact pattern (slot vertices and block ranks, ~220 B per face),
which costs ~10 ms per assembly at 7K faces (3x the assembly there) and little beside the
products at 100K."""

PRODUCT_BLOCK = 2**21
"""Products of slot pairs :meth:`GaussNewtonSystem.normal_equations` computes and scatters at
once (whole slot pairs, at least one): a group with more (its hinges beyond ~40K faces) is
assembled pair by pair, so that its transient memory is that of a block, not of all its
products (16 MB here against ~650 B per face for the hinges at once). Below it the sums are
those of one ``bincount`` per group."""


class GaussNewtonSystem:
    """``J^T J`` (upper triangle) and ``J^T r`` of a :class:`FormEnergy` over its free
    coordinates.

    Args:
        energy: the :class:`solver.refine.form_energy.FormEnergy` (its groups and free vertices
            fix the pattern).

    Attributes:
        n_free: number of free vertices; the unknowns are their ``dim`` coordinates,
            vertex-major (``n_free * dim``).
        index: (n,) int64 position of each vertex among the free ones (-1: fixed).
        diagonal_positions: (n_free * dim,) positions of the diagonal in the CSR values.
    """

    def __init__(self, energy: FormEnergy) -> None:
        self.energy = energy
        self.dim, self.n, self.free = energy.dim, energy.n, energy.free
        self.groups: list[ResidualGroup] = energy.groups
        self.scatters = [_GroupScatter() for _ in self.groups]
        key = self._pattern_key(energy.topology)
        cached = _PATTERNS.get(key)
        if cached is None:
            self._build_pattern()
            _PATTERNS.put(key, self._pattern_state())
        else:
            self._restore_pattern(cached)
        # Small systems keep the positions each assembly computes (see KEPT_POSITIONS_BYTES).
        self._kept: dict[tuple[int, Any], np.ndarray] | None = (
            {} if self._positions_bytes() <= KEPT_POSITIONS_BYTES else None)

    _OBJECTIVE_FIELDS = ("index", "n_free", "indptr", "indices", "nnz",
                         "diagonal_positions")
    _GROUP_FIELDS = ("local", "diag_r", "diag_c", "pair_k", "pair_l", "rank", "twice")

    def _pattern_key(self, topology: MeshTopology) -> bytes:
        """Digest of everything :meth:`_build_pattern` depends on: the faces, the free
        vertices and each group's vertex rows."""
        digest = hashlib.blake2b(digest_size=16)
        digest.update(repr((self.n, self.dim, len(self.groups))).encode())
        for array in (topology.faces, self.free, self.energy.ties.vertices,
                      self.energy.ties.masters, *(g.vertices for g in self.groups)):
            digest.update(repr(array.shape).encode())
            digest.update(np.ascontiguousarray(array).tobytes())
        return digest.digest()

    def _pattern_state(self) -> dict[str, Any]:
        """The arrays :meth:`_build_pattern` made (shared, never written to afterwards)."""
        return {"objective": {f: getattr(self, f) for f in self._OBJECTIVE_FIELDS},
                "groups": [{f: getattr(g, f) for f in self._GROUP_FIELDS}
                           for g in self.scatters]}

    def _restore_pattern(self, state: dict[str, Any]) -> None:
        for name, value in state["objective"].items():
            setattr(self, name, value)
        for g, fields in zip(self.scatters, state["groups"], strict=True):
            for name, value in fields.items():
                setattr(g, name, value)

    def _build_pattern(self) -> None:
        """The scalar CSR pattern of the upper triangle of ``J^T J`` over the free
        coordinates (every diagonal entry stored, for the damping) and, per group, where
        each product of its residuals' gradients lands.

        ``J^T J = sum_rows sum_(k, l) G_k G_l^T`` over a row's vertex slots; only slot pairs
        k <= l are multiplied (their product, or its transpose when vertex l comes first,
        is an upper block; the lower triangle of a diagonal block is dropped), then
        scattered with one ``bincount`` per group straight into the values of the matrix
        that the factorization reads (:func:`solver.linalg.factorize` with
        ``triangle="upper"``): no sparse product, no format conversion.
        """
        dim = self.dim
        index = np.full(self.n, -1, dtype=np.int64)
        index[self.free] = np.arange(int(self.free.sum()))
        ties = self.energy.ties  # tied vertices are their master's unknowns (solver.refine.ties)
        index[ties.vertices] = index[ties.masters]
        self.index = index
        n_free = self.n_free = int(self.free.sum())
        # Block pattern: upper vertex pairs (a <= b) that share a residual, every diagonal.
        parts = [np.arange(n_free, dtype=np.int64) * (n_free + 1)]
        for g in self.groups:
            local = index[g.vertices]
            q = local.shape[1]
            if g.hinge:  # its other pairs are edges, present in the length group
                g_k, g_l = np.array([2]), np.array([3])
            else:
                g_k, g_l = np.triu_indices(q, 1)
            a, b = local[:, g_k], local[:, g_l]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            parts.append(np.where(lo >= 0, lo * n_free + hi, -1).ravel())
        pattern = np.unique(np.concatenate(parts))
        pattern = pattern[pattern >= 0]
        block_rows, block_cols = np.divmod(pattern, max(n_free, 1))
        block_indptr = np.searchsorted(block_rows, np.arange(n_free + 1))
        # Scalar CSR of the upper triangle: row dim*a + r holds the diagonal block's entries
        # c >= r, then dim entries for each upper block (a, b > a), in column order.
        blocks_in_row = np.diff(block_indptr)                       # diagonal included
        r = np.arange(dim)
        row_length = (dim - r)[None, :] + dim * (blocks_in_row[:, None] - 1)  # (n_free, dim)
        indptr = np.zeros(n_free * dim + 1, dtype=np.int64)
        np.cumsum(row_length.ravel(), out=indptr[1:])
        self.indptr = indptr.astype(np.int32)
        # Column of every stored entry, block by block.
        diag_cols = np.concatenate([np.arange(c, dim) for c in range(dim)])  # per row r
        rank = np.arange(len(pattern)) - block_indptr[block_rows]     # 0 = diagonal block
        indices = np.empty(indptr[-1], dtype=np.int64)
        diag_rows = np.repeat(np.arange(dim), dim - np.arange(dim))
        start = indptr[:-1].reshape(n_free, dim)
        # Diagonal blocks.
        pos = start[:, diag_rows] + (diag_cols - diag_rows)[None, :]
        indices[pos.ravel()] = (np.arange(n_free)[:, None] * dim + diag_cols[None, :]).ravel()
        self.diagonal_positions = start.ravel()  # row dim*a + r starts at its entry (r, r)
        # Off-diagonal blocks.
        off = rank > 0
        a, b, k = block_rows[off], block_cols[off], rank[off]
        rr, cc = np.meshgrid(r, r, indexing="ij")
        pos = (start[a][:, rr] + (dim - rr) + dim * (k[:, None, None] - 1) + cc)
        indices[pos.ravel()] = (b[:, None, None] * dim + cc).ravel()
        self.indices = indices.astype(np.int32)
        self.nnz = int(indptr[-1])

        if not n_free:  # every vertex fixed: nothing is gathered (keep the indexing valid)
            start = np.zeros((1, dim), dtype=np.int64)
        for group, g in zip(self.groups, self.scatters, strict=True):
            self._group_pattern(group.vertices, g, pattern, block_indptr, start)

    def _group_pattern(self, vertices: np.ndarray, g: _GroupScatter, pattern: np.ndarray,
                       block_indptr: np.ndarray, start: np.ndarray) -> None:
        """Fill ``g`` for a group of vertex rows ``vertices`` (rows, q), one slot or slot
        pair at a time (int64 temporaries of (rows, dim) or (rows,) only): the block
        ``pattern`` (sorted ``a * n_free + b``), its row pointers ``block_indptr`` and the
        first value position ``start`` (n_free, dim) of every scalar row."""
        dim, n_free, nnz = self.dim, self.n_free, self.nnz
        local = self.index[vertices]
        rows, q = local.shape
        g.local = local.astype(np.int32)
        # Diagonal blocks: G_k[r] G_k[c] for r <= c, at (dim a + r, dim a + c).
        g.diag_r, g.diag_c = np.triu_indices(dim)
        # Off-diagonal pairs k < l: each row's block (lo, hi) of the pair's two vertices, by
        # its rank among the upper blocks of row lo (:func:`_pair_destinations`).
        g.pair_k, g.pair_l = np.triu_indices(q, 1)
        g.rank = np.zeros((len(g.pair_k), rows), dtype=np.int32)
        twice_index, twice_dest = [], []
        for p, (k, m) in enumerate(zip(g.pair_k, g.pair_l, strict=True)):
            a, b = local[:, k], local[:, m]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            valid = (lo >= 0) & (lo != hi)
            lo0 = np.maximum(lo, 0)
            block = np.searchsorted(pattern, np.where(valid, lo * n_free + hi, 0))
            g.rank[p] = np.where(valid, block - block_indptr[lo0] - 1, 0)
            same = np.flatnonzero((a == b) & (a >= 0))
            if len(same):  # the diagonal entries of P + P^T count twice
                dest = _pair_destinations(a[same], b[same], g.rank[p][same], start, nnz)
                for r in range(dim):
                    twice_index.append(((p * dim + r) * dim + r) * rows + same)
                    twice_dest.append(dest[r, r])
        g.twice = ((np.concatenate(twice_index), np.concatenate(twice_dest))
                   if twice_index else None)

    def normal_equations(self, X: np.ndarray, matrix: bool = True,
                         ) -> tuple[float, sp.csr_array | None, np.ndarray]:
        """(E, the upper triangle of the Gauss-Newton matrix over the free coordinates
        (``J^T J`` plus the curvature terms its groups keep, :data:`~solver.refine.residual_groups.
        Curvature`; canonical CSR, every diagonal entry stored; None unless ``matrix``),
        J^T r (n_free * dim,))."""
        dim = self.dim
        given, X = X, self.energy.placed(X)  # tied vertices where their masters put them
        nnz, n = self.nnz, self.n_free * dim
        # The values, and one slot past them where the products of fixed vertices land
        # (dropped): every product is added in place (no (nnz,) sums per block).
        values = np.zeros(nnz + 1) if matrix else None
        gradient = np.zeros(n)
        energy = 0.0
        residuals = []
        for i, (group, g) in enumerate(zip(self.groups, self.scatters, strict=True)):
            r, G = group.evaluate(X)
            residuals.append(r)
            energy += 0.5 * square_sum(r)
            contrib = (r[:, None, None] * G).ravel()            # (rows * q * dim,)
            slots = self._positions((i, "gradient"), lambda g=g: _slot_positions(g.local, n,
                                                                                 dim))
            gradient += np.bincount(slots, contrib, minlength=n + 1)[:n]
            del contrib, slots
            if values is not None:
                self._add_products(values, i, group, g, X, r, G)
        self.energy.remember(given, residuals, "point")  # for the report at this point
        if values is None:
            return energy, None, gradient
        n = self.n_free * dim
        H = sp.csr_array((values[:nnz], self.indices, self.indptr), shape=(n, n))
        H.has_canonical_format = True
        return energy, H, gradient

    def _positions(self, key: tuple[int, Any], compute: Any) -> np.ndarray:
        """``compute()`` (int64 positions), kept under ``key`` where this system keeps them
        (:data:`KEPT_POSITIONS_BYTES`)."""
        if self._kept is None:
            return compute()
        out = self._kept.get(key)
        if out is None:
            out = self._kept[key] = compute()
        return out

    def _positions_bytes(self) -> int:
        """Bytes of every position :meth:`normal_equations` computes (int64)."""
        dim = self.dim
        per_slot = dim  # the gradient's (the diagonal blocks are summed per vertex)
        return 8 * sum(g.local.size * per_slot + len(g.pair_k) * dim * dim * len(g.local)
                       for g in self.scatters)

    def _add_products(self, values: np.ndarray, i: int, group: ResidualGroup,
                      g: _GroupScatter, X: np.ndarray, r: np.ndarray, G: np.ndarray) -> None:
        """Add a group's share of the Gauss-Newton matrix (its residuals ``r`` (rows,) and
        gradients ``G`` (rows, q, dim) at ``X``) to ``values`` (nnz + 1,: the last slot
        takes the fixed vertices' products) in place: diagonal blocks, then the slot
        pairs' products in blocks of :data:`PRODUCT_BLOCK`."""
        nnz = self.nnz
        curvature = None
        if group.curvature is not None:  # r ∇²r kept where it is not small
            curvature = group.curvature(X, r)
        self._add_diagonal_blocks(values, g, G, curvature)
        start = (self.diagonal_positions.reshape(-1, self.dim) if self.n_free
                 else np.zeros((1, self.dim), dtype=np.int64))  # scalar rows' first entries
        Gt = np.ascontiguousarray(np.moveaxis(G, 0, -1))       # (q, dim, rows)
        n_pairs, per_pair = len(g.pair_k), self.dim**2 * len(g.local)
        step = max(1, PRODUCT_BLOCK // max(per_pair, 1))
        for p0 in range(0, n_pairs, step):  # at most q (q - 1) / 2 blocks: 6 for hinges
            p1 = min(p0 + step, n_pairs)
            off = _pair_products(Gt, g.pair_k[p0:p1], g.pair_l[p0:p1])  # (p, dim, dim, rows)
            if curvature is not None and p0 == 0:
                rows, M = curvature
                off[0][:, :, rows] -= M.transpose(1, 2, 0)
            off = off.ravel()
            dest = self._positions((i, p0), lambda p0=p0, p1=p1: _concatenated([
                _pair_destinations(g.local[:, g.pair_k[p]], g.local[:, g.pair_l[p]], g.rank[p],
                                   start, nnz).ravel() for p in range(p0, p1)]))
            np.add.at(values, dest, off)
            del dest
            if g.twice is not None:
                lo, hi = np.searchsorted(g.twice[0], [p0 * per_pair, p1 * per_pair])
                np.add.at(values, g.twice[1][lo:hi], off[g.twice[0][lo:hi] - p0 * per_pair])
            del off

    def _add_diagonal_blocks(self, values: np.ndarray, g: _GroupScatter, G: np.ndarray,
                             curvature: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Add a group's diagonal blocks, ``G_k[r] G_k[c]`` (r <= c) of every slot k (plus
        the curvature terms ``(rows, M)``: M (len(rows), dim, dim) on every slot of those
        rows), to ``values`` (nnz,) in place: one ``bincount`` per entry over the slots'
        free vertices ((n_free,) sums, each added at its vertex's diagonal block), so the
        temporaries are (rows, q) (no (rows, q, entries) products, positions or (nnz,)
        sums: 110 MB of the 100K-face scan's hinges at once). The sums are those of one
        ``bincount`` over every entry (each position's terms in the same order)."""
        n_free, dim = self.n_free, self.dim
        if not n_free:
            return
        slots = g.local.ravel()
        slots = np.where(slots < 0, n_free, slots)             # fixed: one past the end
        blocks = self.diagonal_positions.reshape(-1, dim)      # (n_free, dim) rows' (r, r)
        for r, c in zip(g.diag_r, g.diag_c, strict=True):
            product = G[:, :, r] * G[:, :, c]                  # (rows, q)
            if curvature is not None:
                product[curvature[0]] += curvature[1][:, None, r, c]
            sums = np.bincount(slots, product.ravel(), minlength=n_free + 1)[:n_free]
            values[blocks[:, r] + (c - r)] += sums

    def quadratic_form(self, upper: sp.csr_array, x: np.ndarray) -> float:
        """``x^T H x`` for the symmetric H whose upper triangle is ``upper`` (a matrix of
        :meth:`normal_equations`' pattern)."""
        diagonal = upper.data[self.diagonal_positions]
        return float(2.0 * np.einsum("i,i->", x, upper @ x)
                     - np.einsum("i,i->", x, diagonal * x))


def _slot_positions(local: np.ndarray, n: int, dim: int) -> np.ndarray:
    """(rows * q * dim,) int64 positions in ``J^T r`` (n,) of a group's gradient entries
    from its slots' free vertices ``local`` (rows, q) (-1: fixed, to ``n``, dropped)."""
    slots = local[:, :, None] * np.int64(dim) + np.arange(dim)          # (rows, q, dim)
    slots[local < 0] = n
    return slots.ravel()


def _pair_destinations(a: np.ndarray, b: np.ndarray, rank: np.ndarray, start: np.ndarray,
                       nnz: int) -> np.ndarray:
    """(dim, dim, rows) int64 positions in the Gauss-Newton matrix's values of the products
    ``P[r, c] = G_a[r] G_b[c]`` of one slot pair, from its slots' free vertices ``a``, ``b``
    (rows,) (-1: fixed), the rank of their block among the upper blocks of its row ``rank``
    (rows,) and the first value position ``start`` (n_free, dim) of every scalar row.

    ``P[r, c]`` lands at block (a, b) entry (r, c) when a < b, at block (b, a) entry (c, r)
    when a > b; where a == b (two slots of one vertex, only in degenerate hinges) ``P`` and
    its transpose fold onto the diagonal block's upper triangle; ``nnz`` (dropped) where a
    vertex is fixed."""
    dim = start.shape[1]
    lo = np.minimum(a, b)
    first = start[np.maximum(lo, 0)].T                                    # (dim, rows)
    base = first + dim * rank
    swapped = a > b
    dest = np.empty((dim, dim, len(lo)), dtype=np.int64)  # written entry by entry: no
    for r in range(dim):                                  # (dim, dim, rows) temporaries
        for c in range(dim):
            np.add(base[r], dim - r + c, out=dest[r, c])
            np.add(base[c], dim - c + r, out=dest[r, c], where=swapped)
    same = np.flatnonzero(a == b)
    if len(same):
        r, c = np.arange(dim)[:, None, None], np.arange(dim)[None, :, None]
        dest[:, :, same] = first[np.minimum(r, c), same] + np.abs(c - r)
    dest[:, :, lo < 0] = nnz
    return dest


def _concatenated(parts: list[np.ndarray]) -> np.ndarray:
    """``np.concatenate(parts)``, without a copy of a single part."""
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _pair_products(Gt: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Outer products ``G[row, first] G[row, second]^T`` of gradient slots (``Gt``: the
    gradients rows last, (q, dim, rows)) for slot pairs, as (pairs, dim, dim, rows):
    computed rows last, on contiguous rows, they cost a quarter of the rows-first
    broadcast (30K hinges: 2.4 against 10 ms)."""
    A, B = Gt[first], Gt[second]
    dim = Gt.shape[1]
    out = np.empty((len(first), dim, dim, Gt.shape[2]))
    for r in range(dim):  # the dim rows of each block
        np.multiply(A[:, r, None, :], B, out=out[:, r])
    return out


PATTERN_CACHE_BYTES = 256 * 2**20
"""Bytes of Gauss-Newton patterns (the index arrays of :meth:`GaussNewtonSystem._build_pattern`,
about 220 B per face: 22 MB for a 100K-face scan) a process keeps, most recent first: a new
refinement of a mesh it has seen (another request, another blend value of
:func:`solver.interpolate`, a new handle set of the same sizes) skips the set-up (0.4 s at
100K faces). 0 disables it."""


class _PatternCache:
    """LRU of Gauss-Newton patterns within :data:`PATTERN_CACHE_BYTES`."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._entries: OrderedDict[bytes, tuple[dict[str, Any], int]] = OrderedDict()
        self.counts = {"computed": 0, "cached": 0}

    def get(self, key: bytes) -> dict[str, Any] | None:
        with self._lock:
            entry = self._entries.get(key)
            self.counts["computed" if entry is None else "cached"] += 1
            if entry is None:
                return None
            self._entries.move_to_end(key)
            return entry[0]

    def put(self, key: bytes, state: dict[str, Any]) -> None:
        size = _state_bytes(state)
        with self._lock:
            if size > PATTERN_CACHE_BYTES:
                return
            self._entries[key] = (state, size)
            while sum(n for _, n in self._entries.values()) > PATTERN_CACHE_BYTES:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self.counts = dict.fromkeys(self.counts, 0)

    def info(self) -> dict[str, int]:
        with self._lock:
            return {"entries": len(self._entries),
                    "bytes": sum(n for _, n in self._entries.values()), **self.counts}


def _state_bytes(state: Any) -> int:
    """Bytes of the numpy arrays in a nested pattern state."""
    if isinstance(state, np.ndarray):
        return state.nbytes
    if isinstance(state, dict):
        return sum(_state_bytes(v) for v in state.values())
    if isinstance(state, list | tuple):
        return sum(_state_bytes(v) for v in state)
    return 0


_PATTERNS = _PatternCache()


def pattern_cache_info() -> dict[str, int]:
    """``entries`` and ``bytes`` kept, and how many refinements ``computed`` or reused
    (``cached``) their Gauss-Newton pattern."""
    return _PATTERNS.info()


def clear_pattern_cache() -> None:
    """Forget every kept pattern and reset :func:`pattern_cache_info`'s counters."""
    _PATTERNS.clear()
