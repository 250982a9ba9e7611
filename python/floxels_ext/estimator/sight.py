"""What each support scan could see of the target's points (``FloxelsConfig.range_mask`` and
``visibility``, the ``accurate`` preset): the evidence test and the velocity search count a
support scan only for the points whose own (unmoved) position it could have seen.

Why: the paper's loss compares a point's motion with the scans' points, and a static point that
a support scan did not see looks unmatched under zero flow. Structure whose visible part follows
the sensor -- a long wall or barrier cut by each scan's own range crop, by occluding traffic or by
the beams' reach -- is then better explained by the sensor's motion than by standing still, and
the plain evidence test keeps that motion (bench/RESULTS.md, "What each support scan could see").

* ``range_mask``: the scan's horizontal range band around its sensor (its nearest to its farthest
  point): a cropped scan has no points outside it.
* ``visibility``: the scan's range image (the farthest return per 0.5 x 0.5 degree direction bin
  around its sensor): the scan saw a position when, in its direction, it has a return at least as
  far (``SEEN_MARGIN``): a static point there would have been hit. A nearer return (occlusion) or
  none (the beams missed it) says nothing. The scan's ground returns, which preprocessing removed
  from the points the loss sees, count too where they are given (``ground_points=``): a return
  from the road behind a pedestrian's old place shows the place empty. A direction bin with no
  return at all (the rings of a sparse lidar pass above and below the place) counts as seen where
  the place was *seen through*: the nearest returns below it in its azimuth column and above it
  (within ``THROUGH_BINS``; above, the column may also be empty all the way up: sky, or above
  the beams' reach) all lie beyond it (``SEEN_MARGIN``), and the columns beside it hold no
  return at or before it at its elevation: the beams next to it passed the place, so it is
  empty. A surface the rings skip (a low barrier between two rings' range bands) shows returns
  *at* its range in the bins next to it, or nearer ones (the road in front of it); a gap in
  foliage has returns higher up in its column or beside it: no evidence either way, as before
  (issue 47: an oncoming bus's vacated place, between the rings or under the sky, is seen
  empty; a far barrier between the rings is not).

The point's own position decides, never where a motion takes it, so no motion can escape a
scan's residual by leaving its sight. Everything runs on the device without a host
synchronisation; a scan's sight is built with its distance transform and cached with it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

from floxels_ext.ops._small import device_values

__all__ = ["Sight", "scan_sight", "observed_bits", "self_occluded_bits", "sensor_out_of_reach", "AZ_BIN", "EL_BIN",
           "SEEN_MARGIN", "THROUGH_BINS", "SENSOR_REACH", "SELF_MATCH"]

AZ_BIN = math.radians(0.5)   # range image bins: coarser than a 64-beam lidar's rays, so that a
EL_BIN = math.radians(0.5)   # bin holds a return wherever the scan has one nearby
SEEN_MARGIN = 0.5            # m: a return this much nearer than the point still counts as seeing it
THROUGH_BINS = 4             # elevation bins (2 degrees) searched above and below an empty bin for the
                             # beams next to it: a 32-beam lidar's rings ~1 degree apart, a 16-beam one's 2
NUM_AZ = int(round(2 * math.pi / AZ_BIN))
NUM_EL = int(round(math.pi / EL_BIN)) + 1
SENSOR_REACH = 1000.0        # m: beyond any lidar's range; a "sensor" this far from every point of its
                             # scan is not its sensor (a position in another frame than the scans)
CHUNK_ELEMENTS = 1 << 21     # observed_bits: scans tested together, at most this many (scan, point) pairs
                             # (the seen-through test holds 2 x THROUGH_BINS look-ups of each at once)


@dataclass
class Sight:
    """One support scan's sight: its sensor (3,), its range band (2,: r_min, r_max) or None, its
    range image (NUM_AZ * NUM_EL,: farthest return per bin, -1 where none) or None and with it
    (the seen-through test) ``near``, the nearest return per bin (-1 where none), and ``top``
    (NUM_AZ,) int64, each azimuth column's highest bin with a return (-1 where none); float32
    (``top``: int64) on the scan's device."""

    sensor: torch.Tensor
    band: torch.Tensor | None
    image: torch.Tensor | None
    near: torch.Tensor | None = None
    top: torch.Tensor | None = None

    def tensors(self) -> list[torch.Tensor]:
        return [t for t in (self.sensor, self.band, self.image, self.near, self.top) if t is not None]


def sensor_out_of_reach(sensor, bounds) -> bool:
    """Whether ``sensor`` (xyz) lies more than ``SENSOR_REACH`` from the box ``bounds`` ((min xyz,
    max xyz), host numbers) of its scan's points, so from every point: no lidar saw them from
    there. Such a sight is garbage, and silently so: seen from thousands of km every point falls
    in one or two direction bins, and a position a few km off cuts the range band (issue 42:
    world-frame files far out read with ``--no-ego-motion`` took the world origin as the sensor).
    On the host, from bounds the estimator has anyway: no device synchronisation."""
    lo, hi = bounds
    gap = [max(a - float(s), 0.0, float(s) - b) for s, a, b in zip(sensor[:3], lo, hi)]
    return math.fsum(g * g for g in gap) > SENSOR_REACH ** 2


def warn_sensor_out_of_reach() -> None:
    """The warning that a scan's sensor position is not used (one text: said once per run)."""
    from floxels_ext.estimator.user_warnings import warn_user

    warn_user(f"a scan's sensor position lies more than {SENSOR_REACH:.0f} m from every point of the scan, "
              f"beyond any lidar's range, so it is not where the scan was taken from (a position in "
              f"another frame than the points? floxels run takes each file frame's origin with "
              f"--no-ego-motion: world-frame files need their poses); range_mask and visibility (on in "
              f"the 'accurate' preset) skip such scans, which count everywhere in the evidence test, as "
              f"without sensor positions")


def _bins(rel: torch.Tensor, horiz: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Direction bin and range of positions relative to a sensor (n, 3); ``horiz``: their
    horizontal range ``hypot(rel[:, 0], rel[:, 1])`` if already computed (the same bits)."""
    if horiz is None:
        horiz = torch.hypot(rel[:, 0], rel[:, 1])
    az = torch.atan2(rel[:, 1], rel[:, 0])
    el = torch.atan2(rel[:, 2], horiz)
    ia = ((az + math.pi) / AZ_BIN).floor().long().clamp(0, NUM_AZ - 1)
    ie = ((el + math.pi / 2) / EL_BIN).floor().long().clamp(0, NUM_EL - 1)
    return ia * NUM_EL + ie, torch.linalg.vector_norm(rel, dim=1)


def scan_sight(points: torch.Tensor, sensor, band: bool, image: bool, ground: torch.Tensor | None = None) -> Sight:
    """The sight of a scan (n, 3) float32 from ``sensor`` (xyz in the scans' frame). ``ground``:
    the scan's removed ground returns (m, 3) float32 in the same frame, any device: they join the
    range image (not the band: the scan's crop is that of its points)."""
    # a page-locked copy, not a blocking host-to-device one: nothing here waits for the device
    s = device_values([float(v) for v in sensor[:3]], torch.float32, points.device)
    rel = points.to(torch.float32) - s
    n = rel.shape[0]
    with_ground = image and ground is not None and ground.shape[0] > 0
    if with_ground:  # binned with the points in one pass (each row's arithmetic is its own)
        rel = torch.cat([rel, ground.to(device=points.device, dtype=torch.float32) - s])
    # (column views of rel: the same element-wise path as before the ground joined them)
    horiz = torch.hypot(rel[:, 0], rel[:, 1]) if band or image else None
    b = img = near = top = None
    if band:
        b = torch.stack(list(torch.aminmax(horiz[:n])))
    if image:
        idx, rr = _bins(rel, horiz)
        r_far = r_near = rr  # the ranges the farthest and the nearest return per bin are taken of
        if with_ground:  # non-finite ground rows: no return (no host synchronisation; the points are finite)
            ok = torch.isfinite(rel).all(dim=1)
            idx = torch.where(ok, idx, torch.zeros_like(idx))
            r_far = torch.where(ok, rr, torch.full_like(rr, -1.0))
            r_near = torch.where(ok, rr, torch.full_like(rr, math.inf))
        img = torch.full((NUM_AZ * NUM_EL,), -1.0, dtype=torch.float32, device=points.device)
        img.scatter_reduce_(0, idx, r_far, "amax")  # a maximum: the same bits in any order
        near = torch.full_like(img, math.inf).scatter_reduce_(0, idx, r_near, "amin")
        near = torch.where(img >= 0, near, torch.full_like(near, -1.0))
        el = torch.arange(NUM_EL, device=points.device)
        top = torch.where(img.view(NUM_AZ, NUM_EL) >= 0, el, -1).amax(dim=1)
    return Sight(s, b, img, near, top)


def observed_bits(points: torch.Tensor, sights: list[Sight | None], occluded: bool = False):
    """(n,) int32: bit k set where support scan k could see the point's position (a scan
    without a sight counts everywhere); the ``observed`` of ``floxels::dt_evidence`` /
    ``dt_residual``. The scans are tested together, a few at a time (CHUNK_ELEMENTS): one scan
    at a time, the ~20 small launches per scan (120-240 a window of the accurate preset) kept
    the optimiser thread busy while the GPU idled (``floxels run``, bench/RESULTS.md). Each
    element's arithmetic is that of one scan alone: the same bits.

    ``occluded``: also (second of a pair) the bits of the scans whose range image has a return
    *nearer* than the point in its direction (something stood in front of the place: it was
    hidden, not out of the beams' reach), from the same look-ups (issue 47: a group that no scan
    saw because each showed something in front of it keeps its flow)."""
    p = points.to(torch.float32)
    n = p.shape[0]
    bits = torch.zeros(n, dtype=torch.int32, device=p.device)
    hidden = torch.zeros(n, dtype=torch.int32, device=p.device)
    for k, s in enumerate(sights):
        if s is None:  # (bit 31 wraps to the sign bit, as the kernels read it)
            bits |= torch.ones(n, dtype=torch.int32, device=p.device) << k
    have = [k for k, s in enumerate(sights) if s is not None]
    step = max(1, CHUNK_ELEMENTS // max(n, 1))
    for c in range(0, len(have), step):
        ks = have[c:c + step]
        seen, front = _seen(p, [sights[k] for k in ks], ks)
        bits |= seen
        hidden |= front
    return (bits, hidden) if occluded else bits


def _seen(p: torch.Tensor, sights: list[Sight], ks: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """(n,) int32 with bit ks[j] set where sights[j] saw the point (see :func:`observed_bits`),
    and (n,) int32 with it set where its range image has a nearer return in the point's direction."""
    n, K = p.shape[0], len(sights)
    rel = p[None] - torch.stack([s.sensor for s in sights])[:, None]  # (K, n, 3)
    ok = front = None  # (K, n) bool; None: every scan saw the point / none shows a nearer return

    def where_scans(js: list[int], v: torch.Tensor, fill: bool) -> torch.Tensor:
        # v for the scans js (rows of it), fill for the others (every scan has one: v itself)
        if len(js) == K:
            return v
        out = torch.full((K, n), fill, dtype=torch.bool, device=p.device)
        return out.index_copy_(0, rows(js), v)

    def rows(js: list[int]) -> torch.Tensor:
        # the scans js as a device index: indexing a CUDA tensor with a Python list copies the list
        # from pageable memory, which waits for the stream's queued work (5 % of an accurate
        # engine's GPU-feeding thread in floxels run: py-spy, H100)
        return device_values(js, torch.int64, p.device)

    band = [j for j, s in enumerate(sights) if s.band is not None]
    if band:
        lim = torch.stack([sights[j].band for j in band])  # (B, 2)
        sel = rows(band)  # (rows gathered: contiguous, the element-wise path as before)
        r = torch.hypot(rel[:, :, 0].index_select(0, sel), rel[:, :, 1].index_select(0, sel))
        ok = where_scans(band, (r >= lim[:, :1]) & (r <= lim[:, 1:]), True)
    image = [j for j, s in enumerate(sights) if s.image is not None]
    if image:
        imgs = torch.stack([sights[j].image for j in image])  # (I, bins)
        nears = torch.stack([sights[j].near for j in image])
        tops = torch.stack([sights[j].top for j in image])  # (I, NUM_AZ)
        idx, rr = _bins((rel if len(image) == K else rel.index_select(0, rows(image))).reshape(-1, 3))
        idx = idx.view(len(image), n) + torch.arange(len(image), device=p.device)[:, None] * imgs.shape[1]
        ret = imgs.view(-1)[idx]
        rr = rr.view(len(image), n)
        near = rr - SEEN_MARGIN
        seen = where_scans(image, (ret >= near) | _through(nears.view(-1), tops, idx, ret, rr + SEEN_MARGIN), True)
        ok = seen if ok is None else ok & seen
        front = where_scans(image, (ret >= 0) & (ret < near), False)
    if ok is None:
        ok = torch.ones(K, n, dtype=torch.bool, device=p.device)
    if front is None:
        front = torch.zeros(K, n, dtype=torch.bool, device=p.device)
    shifts = device_values(ks, torch.int32, p.device)[:, None]
    # distinct bits: the sums are their ORs
    return ((ok.to(torch.int32) << shifts).sum(0, dtype=torch.int32),
            (front.to(torch.int32) << shifts).sum(0, dtype=torch.int32))


@functools.lru_cache(maxsize=16)
def _steps(device: torch.device, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_through`'s constant offsets on ``device``, made once: the elevation steps (2,
    ``bins``) above (1..) and below (-1..) a bin, and the azimuth steps (2,) to the columns
    beside it."""
    d = list(range(1, bins + 1))
    return (device_values([d, [-x for x in d]], torch.int64, device), device_values([-1, 1], torch.int64, device))


def _through(flat: torch.Tensor, tops: torch.Tensor, idx: torch.Tensor, ret: torch.Tensor,
             far: torch.Tensor) -> torch.Tensor:
    """(I, n) bool: the point's bin (``idx`` into the stacked nearest-return images ``flat``, its
    return ``ret``, -1 where none) is empty; the nearest non-empty bin below it in its azimuth
    column within ``THROUGH_BINS``, and the nearest above it there (or none in the whole column
    above it: ``tops``, each column's highest non-empty bin), have every return at ``far`` or
    beyond; the bins beside it at its elevation hold none before ``far`` (see the module's
    docstring). Measured (bench/RESULTS.md, issue 47's sixth-session section): the nearest return
    of a bin, not its farthest, because a bin at a barrier's top edge holds both the barrier and
    the road beyond it (the farthest alone read a median barrier's own points as seen through:
    simulated highway, tuning seed 0, a 197-point group kept the ego's motion, static EPE of that
    frame 0.007 -> 0.045). Sky above counted only where the whole column above is empty, and
    the columns beside the place checked: with an empty side anywhere counted, the AV2 pair's
    static foliage 3-10 m up (small groups the other sweep missed) took 0.66 m/frame on 40 points
    (static EPE 0.0070 -> 0.0074); with both checks 23 points (0.0073)."""
    if THROUGH_BINS <= 0:  # no bins searched: no nearest return below, so never seen through
        return torch.zeros_like(ret, dtype=torch.bool)
    ie = idx % NUM_EL  # the elevation bin (each image is NUM_EL-bin columns)
    # the THROUGH_BINS bins above and below, in one gather (I, n, 2, THROUGH_BINS): few launches
    # from the thread that feeds the GPU (a loop over the bins took ~60)
    steps, beside = _steps(idx.device, THROUGH_BINS)
    e = ie[..., None, None] + steps
    v = torch.where((e >= 0) & (e < NUM_EL), flat[(idx[..., None, None] + steps).clamp(0, flat.numel() - 1)], -1.0)
    # the nearest return on each side: the first bin with one (argmax: the first of equal
    # maxima), -1 where none (the first bin's -1 then)
    first = (v >= 0).to(torch.uint8).argmax(dim=-1, keepdim=True)
    side = v.gather(-1, first).squeeze(-1)  # (I, n, 2)
    ok = side >= far[..., None]
    # above: or nothing above at all in the column
    above = ok[..., 0] | ((side[..., 0] < 0) & (ie > tops.view(-1)[idx // NUM_EL]))
    through = (ret < 0) & above & ok[..., 1]
    # the open place reaches the azimuth columns beside it at its elevation (no return there, or
    # only beyond it): a hole in foliage has the foliage beside it
    local = idx % (NUM_AZ * NUM_EL)
    ia = local // NUM_EL
    v = flat[(idx - local + ie)[..., None] + (ia[..., None] + beside) % NUM_AZ * NUM_EL]  # (azimuth wraps around)
    return through & ((v < 0) | (v >= far[..., None])).all(dim=-1)


_RANGE_BITS = 20   # self_occluded_bits: a moved point's range in mm below its (group, bin) key
SELF_MATCH = 2 * SEEN_MARGIN  # m: the scan's nearest return in the bin within this of the moved group's


def self_occluded_bits(points: torch.Tensor, flow: torch.Tensor, run: torch.Tensor, cand: torch.Tensor,
                       occluded: torch.Tensor, sights: list[Sight | None], offsets) -> torch.Tensor:
    """(n,) int32: bit k set where support scan k shows the point's own (unmoved) position behind
    a nearer return (its ``occluded`` bit, :func:`observed_bits`) and that return is the point's
    group itself, moved by its flow: in scan k's range image (its sensor, the module's bins) the
    group's points moved by ``t_k * flow`` (``offsets``: the scans' time offsets) have one in the
    point's direction bin at least ``SEEN_MARGIN`` nearer than the point, and the scan's nearest
    return in that bin lies within ``SELF_MATCH`` of it (issue 47: a pedestrian walking the
    ego's way hides its old place behind itself in the scans of the side it walks to; static
    structure behind passing traffic is hidden by *another* object, and its own moved points
    slide along its surface, not in front of it). Only the points of ``cand`` (bool) groups
    (``run``: each point's group number, any int64 ids < n) are tested and build the images;
    the others get 0. One sort of the candidates' moved points a scan (the others keyed past
    every real key), no host synchronisation on a GPU (on the CPU, where that costs nothing, no
    work without a candidate)."""
    p = points.to(torch.float32)
    f = flow.to(torch.float32)
    n = p.shape[0]
    out = torch.zeros(n, dtype=torch.int32, device=p.device)
    # no candidate: nothing to test (asked on the CPU only, where it costs no synchronisation;
    # the sorts below cost ~0.09 s a frame there, for every one-sided window)
    if n == 0 or (p.device.type == "cpu" and not bool(cand.any())):
        return out
    nb = NUM_AZ * NUM_EL
    lim = (1 << _RANGE_BITS) - 1
    gkey = run.long() * nb
    past = torch.full_like(gkey, (n + 1) * nb << _RANGE_BITS)
    for k, (s, t) in enumerate(zip(sights, offsets)):
        if s is None or s.image is None:
            continue
        pi, pr = _bins(p - s.sensor)
        qi, qr = _bins(p + float(t) * f - s.sensor)
        mm = (qr * 1000.0).round().clamp(0, lim).long()
        key = torch.where(cand, ((gkey + qi) << _RANGE_BITS) | mm, past)
        sk, _ = torch.sort(key)
        want = (gkey + pi) << _RANGE_BITS
        pos = torch.searchsorted(sk, want).clamp_max(n - 1)
        hit = sk[pos]
        same = (hit >> _RANGE_BITS) == (want >> _RANGE_BITS)
        r_self = (hit & lim).to(torch.float32) / 1000.0
        near = s.near[pi]
        mine = (cand & same & (r_self < pr - SEEN_MARGIN) & (((occluded >> k) & 1) != 0)
                & (near >= 0) & ((near - r_self).abs() <= SELF_MATCH))
        out |= mine.to(torch.int32) << k
    return out
