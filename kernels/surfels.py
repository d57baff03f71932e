"""Surfel storage: the arrays of a map, the pool they come from, growth, and copies to and from NumPy.

A surfel is a small oriented disc: position, normal, colour, weight (confidence), radius and the frames
it was created and last updated in. A map keeps them as a structure of arrays (one Taichi field per
attribute) of a fixed capacity, beside the per-surfel scratch of the kernels that run over the map;
``SurfelStore.ensure_capacity`` grows them (reallocate ×2 and copy, on the Taichi side) or raises
``MapCapacityError`` before a write could go past the end.

Taichi allows a limited number of SNode trees per program, and freeing one makes it recompile every
kernel, so arrays and work images are pooled (``Pool``): a garbage-collected map's arrays wait there for
the next map of the same capacity, and every map shares one set of work images per resolution. Other
per-owner objects whose fields kernels take (a SLAM object's frame pyramids) are lent the same way
(``Pool.lend``).
"""

import weakref

import numpy as np
import taichi as ti
from taichi.lang import impl

from ti_fusion.backend import check_started, current_backend
from ti_fusion.errors import MapCapacityError
from ti_fusion.kernels.common import BLOCK, data_oriented

# Fields of one surfel, in the order of ``SurfelArrays.attributes``.
ATTRIBUTES = ("position", "normal", "color", "weight", "radius", "t_created", "t_updated")
# Stored beside them and moved with them (compaction, growth), but not part of the fused geometry that the
# references compare: the anchor (keyframe id) of the frame that last created or updated the surfel.
STORED = ATTRIBUTES + ("anchor",)


@data_oriented
class SurfelArrays:
    """The surfel attributes (structure of arrays) and the per-surfel scratch, for one capacity.

    Allocated in its own SNode tree so that growing a map can free the old arrays.
    """

    def __init__(self, capacity: int):
        self.capacity = int(capacity)
        self.blocks = self.capacity // BLOCK + 1  # BLOCK surfels per block; the last one may be partial
        fb = ti.FieldsBuilder()
        self.position = ti.Vector.field(3, ti.f32)  # world frame, metres
        self.normal = ti.Vector.field(3, ti.f32)  # world frame, unit
        self.color = ti.Vector.field(3, ti.f32)  # RGB in [0, 255]
        self.weight = ti.field(ti.f32)  # confidence: sum of measurement weights
        self.radius = ti.field(ti.f32)  # metres
        self.t_created = ti.field(ti.i32)  # frame index
        self.t_updated = ti.field(ti.i32)  # frame index of the last merge
        # the anchor (keyframe id) of the last frame that created or updated the surfel: loop closure moves
        # the surfel with that anchor's pose correction (``fusion.apply_corrections``)
        self.anchor = ti.field(ti.i32)

        # The last projection into an image (``index_map``): every surfel's pixel (v·W + u, or -1 when
        # the projection left it out) and depth key (``depth_bits``); the surfels it kept, listed per
        # block (block b's ``block_listed[b]`` at ``listed_by_block[b·BLOCK:]``), then gathered in index
        # order (``listed[:n_listed]``, block b's from ``listed_offset[b]``).
        self.proj_pixel = ti.field(ti.i32)
        self.proj_depth = ti.field(ti.i32)
        self.listed_by_block = ti.field(ti.i32)
        self.listed = ti.field(ti.i32)

        # Removal (``fusion``: in-place compaction to a new count m): the surfels to remove, listed per
        # block in index order (``block_removals[b]`` at ``removals_by_block[b·BLOCK:]``); the holes they
        # leave below m and the survivors at or above m that fill them (as many of each: at most half the
        # map), in index order.
        self.removals_by_block = ti.field(ti.i32)
        for f in (self.position, self.normal, self.color, self.weight, self.radius, self.t_created,
                  self.t_updated, self.anchor, self.proj_pixel, self.proj_depth, self.listed_by_block,
                  self.listed, self.removals_by_block):
            fb.dense(ti.i, self.capacity).place(f)  # one array per attribute: SoA
        self.holes = ti.field(ti.i32)
        self.movers = ti.field(ti.i32)
        for f in (self.holes, self.movers):
            fb.dense(ti.i, self.capacity // 2 + 1).place(f)

        self.block_listed = ti.field(ti.i32)
        self.listed_offset = ti.field(ti.i32)
        self.block_removals = ti.field(ti.i32)
        self.block_holes = ti.field(ti.i32)  # block b's removals below m
        self.hole_offset = ti.field(ti.i32)  # where block b's holes start in ``holes``
        self.mover_offset = ti.field(ti.i32)  # where block b's movers start in ``movers``
        for f in (self.block_listed, self.listed_offset, self.block_removals, self.block_holes,
                  self.hole_offset, self.mover_offset):
            fb.dense(ti.i, self.blocks).place(f)
        self.n_listed = ti.field(ti.i32)
        self.n_holes = ti.field(ti.i32)
        for f in (self.n_listed, self.n_holes):
            fb.place(f)
        self.tree = fb.finalize()

    @property
    def attributes(self):
        return [getattr(self, name) for name in ATTRIBUTES]

    def destroy(self) -> None:
        self.tree.destroy()


class Pool:
    """Taichi fields shared by every surfel map of the running Taichi program, and surfel arrays to reuse.

    The arrays of a garbage-collected map go back here for the next map of the same capacity instead of
    being freed; work images (one object per kind and resolution, e.g. ``fusion.FusionImages``) and small
    fields are made once and shared; objects lent to an owner (``lend``) come back when it is collected.
    Everything is dropped when Taichi starts a new program.
    """

    _runtime = None  # weak reference to the Taichi runtime the fields belong to
    images: dict[tuple[type, int, int], object] = {}
    small: dict[str, object] = {}
    # objects whose owners are gone (surfel arrays by (SurfelArrays, capacity), lent objects by their key)
    spares: dict[tuple, list] = {}

    @classmethod
    def current(cls) -> type["Pool"]:
        runtime = impl.get_runtime()
        if cls._runtime is None or cls._runtime() is not runtime:  # a new program (ti.reset / init)
            cls._runtime = weakref.ref(runtime)
            cls.images, cls.small, cls.spares = {}, {}, {}
        return cls

    @classmethod
    def lend(cls, owner, key: tuple, make):
        """An object for ``owner`` to use until ``owner`` is garbage-collected: one that an earlier owner
        had for the same ``key`` (what ``make`` depends on), else ``make()``. Taichi compiles a kernel once
        per set of fields it is given, so a second SLAM object with new fields compiles (or loads) every
        kernel again, seconds on a CPU; with the first one's fields it compiles nothing."""
        obj = cls._spare(key)
        if obj is None:
            obj = make()
        weakref.finalize(owner, cls.give_back, cls._runtime, key, obj)
        return obj

    @classmethod
    def _spare(cls, key: tuple):
        """An object given back for ``key``, or None."""
        try:  # one pop and no test before it: two threads may ask at once
            return cls.current().spares.get(key, []).pop()
        except IndexError:
            return None

    @classmethod
    def give_back(cls, runtime_ref, key: tuple, obj) -> None:
        """``obj`` (made for ``key``) waits for the next taker, unless its program has ended."""
        if cls._runtime is not None and cls._runtime is runtime_ref and runtime_ref() is not None:
            cls.spares.setdefault(key, []).append(obj)

    @classmethod
    def take_arrays(cls, capacity: int) -> SurfelArrays:
        spare = cls._spare((SurfelArrays, capacity))
        return SurfelArrays(capacity) if spare is None else spare

    @classmethod
    def image_set(cls, kind: type, height: int, width: int):
        """The one ``kind(height, width)`` of this program (made on first use)."""
        pool = cls.current()
        key = (kind, height, width)
        if key not in pool.images:
            pool.images[key] = kind(height, width)
        return pool.images[key]

    @classmethod
    def field(cls, name: str, make):
        """The one field called ``name`` of this program (``make()`` on first use)."""
        pool = cls.current()
        if name not in pool.small:
            pool.small[name] = make()
        return pool.small[name]


class ThisStart:
    """An attribute holding Taichi objects of the start of Taichi its owner was made on (``owner._generation``):
    read after ``init_backend`` started Taichi again, it raises BackendMisuse, since a kernel or read-back on the
    freed fields would crash the process."""

    def __set_name__(self, owner, name: str) -> None:
        self.slot = "_taichi_" + name.lstrip("_")

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        check_started(obj._generation, f"the surfel map ({type(obj).__name__}; DenseSLAM.mapper.map)")
        return getattr(obj, self.slot)

    def __set__(self, obj, value) -> None:
        setattr(obj, self.slot, value)


class SurfelStore:
    """``count`` live surfels at indices [0, count) of pooled ``SurfelArrays``, growable."""

    arrays = ThisStart()

    def __init__(self, capacity: int = 4_000_000, grow: bool = True):
        if capacity < 1:
            raise MapCapacityError(f"fusion.capacity must be positive (got {capacity})")
        self._generation = current_backend().generation  # every use of its fields checks it (ThisStart)
        self.grow = grow
        self.count = 0
        self._projected = 0  # surfels [0, _projected) have a current fusion projection (proj_pixel, proj_depth)
        self._adopt(Pool.take_arrays(int(capacity)))

    def _adopt(self, arrays: SurfelArrays) -> None:
        """Use ``arrays`` from now on; they go back to the pool when this map is garbage-collected."""
        if getattr(self, "_finalizer", None) is not None:
            self._finalizer.detach()
        self.arrays = arrays
        self._finalizer = weakref.finalize(self, Pool.give_back, Pool._runtime, (SurfelArrays, arrays.capacity),
                                           arrays)

    @property
    def capacity(self) -> int:
        return self.arrays.capacity

    def ensure_capacity(self, needed: int) -> None:
        """Make room for ``needed`` surfels in total: grow ×2 until they fit, or raise MapCapacityError."""
        if needed <= self.capacity:
            return
        if not self.grow:
            raise MapCapacityError(
                f"surfel map full: {self.count} surfels + {needed - self.count} new > capacity {self.capacity}; "
                f"raise fusion.capacity (e.g. --set fusion.capacity={2 * needed}) or allow fusion.grow")
        capacity = self.capacity
        while capacity < needed:
            capacity *= 2
        new = SurfelArrays(capacity)
        copy_all(self.arrays, new, self.count)
        old = self.arrays
        self._adopt(new)
        # Freed rather than pooled: a grown map is large. Taichi then recompiles its kernels (once).
        old.destroy()
        self._projected = 0  # the scratch was not copied

    def clear(self) -> None:
        self.count = 0
        self._projected = 0

    def to_numpy(self, names=ATTRIBUTES, stride: int = 1) -> dict[str, np.ndarray]:
        """The live surfels as NumPy arrays (copies), keyed by attribute name; with ``stride`` k, every k-th
        surfel only (a cheap, deterministic subsample for logging); ``names`` may hold ``anchor`` too (STORED).
        Only those surfels are copied, not the whole capacity the fields hold."""
        stride = max(1, int(stride))
        m = (self.count + stride - 1) // stride
        out = {}
        for name in names:
            field = getattr(self.arrays, name)
            dtype = np.float32 if field.dtype == ti.f32 else np.int32
            out[name] = np.empty((m, 3) if getattr(field, "n", 1) == 3 else m, dtype)
        if m and set(names) <= set(STORED):  # one launch, one kernel instance for every such export
            asked = sum(1 << j for j, name in enumerate(STORED) if name in out)
            export_stored(self.arrays, m, stride, asked, *(out.get(name, _NOT_ASKED[name]) for name in STORED))
        elif m:
            for name in names:
                export = export_vector if out[name].ndim == 2 else export_scalar
                export(getattr(self.arrays, name), out[name], stride)
        return out

    def from_numpy(self, data: dict[str, np.ndarray]) -> None:
        """Replace the surfels by the given ones (every attribute of ATTRIBUTES, same length; ``anchor``
        too if given, else 0)."""
        n = len(data["position"])
        self.ensure_capacity(n)
        for name in STORED:
            field = getattr(self.arrays, name)
            full = field.to_numpy()
            full[:n] = data[name] if name in data else 0
            field.from_numpy(full)
        self.count = n
        self._projected = 0


@ti.func
def copy_surfel(src: ti.template(), i, dst: ti.template(), k):
    """Surfel i of ``src`` to index k of ``dst`` (the attributes and the anchor; no scratch)."""
    dst.position[k] = src.position[i]
    dst.normal[k] = src.normal[i]
    dst.color[k] = src.color[i]
    dst.weight[k] = src.weight[i]
    dst.radius[k] = src.radius[i]
    dst.t_created[k] = src.t_created[i]
    dst.t_updated[k] = src.t_updated[i]
    dst.anchor[k] = src.anchor[i]


@ti.kernel
def copy_all(src: ti.template(), dst: ti.template(), n: ti.i32):
    for i in range(n):
        copy_surfel(src, i, dst, i)


@ti.kernel
def export_vector(src: ti.template(), out: ti.types.ndarray(), stride: ti.i32):
    """out[k] = src[k · stride] for the rows of ``out``: the live prefix (or a subsample) of one attribute,
    without copying the whole capacity as ``field.to_numpy()`` would."""
    for k in range(out.shape[0]):
        for c in ti.static(range(3)):
            out[k, c] = src[k * stride][c]


@ti.kernel
def export_scalar(src: ti.template(), out: ti.types.ndarray(), stride: ti.i32):
    for k in range(out.shape[0]):
        out[k] = src[k * stride]


# export_stored's parameters and _NOT_ASKED's dtypes follow this order: a reordered STORED must change them too
assert STORED == ("position", "normal", "color", "weight", "radius", "t_created", "t_updated", "anchor"), STORED

# the outputs of ``export_stored`` not asked for (a row, not none: a GPU backend copies each array to the
# device and back), with the dtype and dimensions of those asked for
_NOT_ASKED = {name: np.zeros((1, 3) if name in ("position", "normal", "color") else 1,
                             np.int32 if name in ("t_created", "t_updated", "anchor") else np.float32)
              for name in STORED}


@ti.kernel
def export_stored(s: ti.template(), m: ti.i32, stride: ti.i32, asked: ti.i32, position: ti.types.ndarray(),
                  normal: ti.types.ndarray(), color: ti.types.ndarray(), weight: ti.types.ndarray(),
                  radius: ti.types.ndarray(), t_created: ti.types.ndarray(), t_updated: ti.types.ndarray(),
                  anchor: ti.types.ndarray()):
    """Row k < m of each output asked for (bit j of ``asked``: STORED[j]): surfel k · stride's attribute.
    The exports of a run (map.ply, the saved map, the log's snapshots) are one kernel instance instead of one
    per attribute (``export_vector``, ``export_scalar``), each of which costs its first launch
    (docs/PERFORMANCE.md)."""
    for k in range(m):
        i = k * stride
        if asked & 1:
            for c in ti.static(range(3)):
                position[k, c] = s.position[i][c]
        if asked & 2:
            for c in ti.static(range(3)):
                normal[k, c] = s.normal[i][c]
        if asked & 4:
            for c in ti.static(range(3)):
                color[k, c] = s.color[i][c]
        if asked & 8:
            weight[k] = s.weight[i]
        if asked & 16:
            radius[k] = s.radius[i]
        if asked & 32:
            t_created[k] = s.t_created[i]
        if asked & 64:
            t_updated[k] = s.t_updated[i]
        if asked & 128:
            anchor[k] = s.anchor[i]
