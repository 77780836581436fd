"""Training samples: context pairs and target views drawn from posed data sets, and their loader.

**Candidate pairs**: :mod:`.pairs` (which ordered pairs of frames are contexts, and their targets).

**Samples** (:class:`PairDataset`). Sample ``i`` of an epoch uses pair ``i`` (every candidate once per
epoch), or — with ``samples_per_epoch`` — pair ``perm[i mod P]`` of a per-epoch permutation, or — with
``per_scene`` (``per_scene × scenes`` samples an epoch) — a pair drawn scene first
(:meth:`~.pairs.CandidatePairs.draw_by_scene`) with ``(seed, epoch, i)``. Its
``targets`` target views are drawn from the pair's candidates without replacement (with repetition
when the pair has fewer). Every draw comes from a generator seeded with ``(seed, epoch, i)`` only, so a
sample does not depend on the worker that makes it, nor on the order of the requests.

**Images** (:func:`resize_and_crop`): scaled, keeping the aspect ratio, to the smallest size covering
``size`` = (W, H), then centre-cropped to ``size``; ``K`` is scaled by the per-axis resize factors and
shifted by the crop offset (exact with macsplat's pixel-centre-at-+0.5 convention). With
``crop="principal-point"`` the image (and depth) is first cut to the largest window centred on the
principal point (:func:`~macsplat_cli.camera_math.principal_point_window`), as the MAC-Splat release does.

**Unreadable images.** A sample with an image that cannot be decoded is replaced by another one drawn
with ``(seed, epoch, i, attempt)``; each file is named once in a warning, and ``PairDataset.skipped``
counts the samples each file made skip (with :func:`make_loader`, counted in the main process whatever
the number of workers). When every image is unreadable, or no readable sample turns up after
:data:`MAX_ATTEMPTS` draws, :class:`~macsplat_cli.errors.DatasetError`.

**Loader** (:func:`make_loader`): a :class:`torch.utils.data.distributed.DistributedSampler` (seeded;
with ``world_size = 1`` it is a plain seeded shuffle), so the ranks of a world split one permutation
without overlap; :meth:`PairLoader.set_epoch` moves the sampler and the draws to another epoch.
"""

from __future__ import annotations

import itertools
import logging
import random
from collections.abc import Iterator, Sequence
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate
from torch.utils.data.distributed import DistributedSampler

from ..camera_math import principal_point_window
from ..datasets import EvalDataset, EvalScene, resize_depth_nearest
from ..errors import DatasetError, ImageReadError, InputError
from ..images import load_image
from .pairs import CandidatePairs, PairSamplingConfig, TrainPair, candidate_pairs

__all__ = [
    "MAX_ATTEMPTS",
    "CandidatePairs",
    "PairDataset",
    "PairLoader",
    "PairSamplingConfig",
    "TrainPair",
    "candidate_pairs",
    "make_loader",
    "resize_and_crop",
]

logger = logging.getLogger(__name__)

MAX_ATTEMPTS = 100
"""Most draws for one sample before giving up on unreadable images."""
_SAMPLE_TAG = 0x5A17
_PERM_TAG = 0x9E12
_SCENE_TAG = 0x5CE7


# ------------------------------------------------------------------------------------ images
def _fit(width: int, height: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """(resized W, resized H, crop x0, crop y0) of the aspect-preserving cover-and-centre-crop."""
    W, H = size
    s = max(W / width, H / height)
    rw, rh = max(W, round(width * s)), max(H, round(height * s))
    return rw, rh, (rw - W) // 2, (rh - H) // 2


def resize_and_crop(image: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Scale an image to cover ``size`` = (W, H) keeping its aspect ratio, centre-crop, and adjust ``K``.

    Args:
        image: ``[h, w, C]`` or ``[h, w]``.
        K: intrinsics of ``image`` (pixel centres at +0.5). [3, 3]
        size: output (W, H).

    Returns:
        ``(image [H, W, C], K [3, 3] float64)``: ``K`` row 0 is scaled by ``W'/w`` and row 1 by
        ``H'/h`` (``W' × H'`` the resized size), then ``cx -= x0``, ``cy -= y0`` (the crop's corner).
        The image is resampled bilinearly at pixel centres, antialiased when shrinking; float32.
    """
    h, w = image.shape[:2]
    rw, rh, x0, y0 = _fit(w, h, size)
    if (rw, rh) != (w, h):
        # torch, not OpenCV: OpenCV's thread pool can deadlock in forked loader workers
        t = torch.from_numpy(np.ascontiguousarray(image, np.float32))
        t = t[None, None] if t.ndim == 2 else t.permute(2, 0, 1)[None]
        t = F.interpolate(t, size=(rh, rw), mode="bilinear", antialias=rw < w or rh < h, align_corners=False)
        image = (t[0, 0] if image.ndim == 2 else t[0].permute(1, 2, 0)).numpy()
    W, H = size
    out = np.ascontiguousarray(image[y0 : y0 + H, x0 : x0 + W])
    K2 = np.array(K, dtype=np.float64)
    K2[0] *= rw / w
    K2[1] *= rh / h
    K2[0, 2] -= x0
    K2[1, 2] -= y0
    return out, K2


def _crop_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    h, w = depth.shape
    rw, rh, x0, y0 = _fit(w, h, size)
    d = resize_depth_nearest(depth, rw, rh)
    return np.ascontiguousarray(d[y0 : y0 + size[1], x0 : x0 + size[0]])


class _Unreadable(Exception):
    def __init__(self, path: str, reason: str) -> None:
        super().__init__(path)
        self.path, self.reason = path, reason


# ------------------------------------------------------------------------------------ dataset
class PairDataset(Dataset):
    """Training samples of two context views and ``config.targets`` target views (module docstring).

    ``dataset[i]`` is a dict of tensors (``T = config.targets``, ``(W, H) = config.size``):

    * ``"context"``: ``[2, 3, H, W]`` float32 in [0, 1]; ``"context_K"``: ``[2, 3, 3]`` float64 (of the
      resized, cropped image, pixel centres at +0.5); ``"context_c2w"``: ``[2, 4, 4]`` float64 (world);
    * ``"target"``: ``[T, 3, H, W]``; ``"target_K"``: ``[T, 3, 3]``; ``"target_c2w"``: ``[T, 4, 4]``;
    * ``"index"``: the sample index ``i``, int64 scalar;
    * with ``depth=True``: ``"context_depth"`` ``[2, H, W]`` and ``"target_depth"`` ``[T, H, W]`` float32
      (ground truth, nearest-resized and cropped like the image; 0 = none or a frame without depth).

    Attributes:
        skipped: per unreadable image file, the number of samples it made skip (in this process).

    Raises:
        DatasetError: no pair, or a pair pointing outside the data set.
    """

    def __init__(
        self,
        dataset: EvalDataset,
        pairs: Sequence[TrainPair],
        config: PairSamplingConfig,
        *,
        seed: int = 0,
        epoch: int = 0,
        depth: bool = False,
    ) -> None:
        if not len(pairs):
            raise DatasetError(f"{dataset.root}: no training pair")
        # compact arrays, not a list of Python objects: cheap to fork or pickle into workers
        self._pairs = CandidatePairs.from_pairs(pairs)
        self._pairs.validate(dataset)
        self.dataset = dataset
        self.config = config
        self.seed = int(seed) % 2**63
        self.epoch = int(epoch)
        self.depth = bool(depth)
        self._images: set[str] | None = None  # every image the pairs name, listed on the first unreadable one
        self.skipped: dict[str, int] = {}
        self._bad: dict[str, str] = {}
        self._perms: dict[tuple[int, int], np.ndarray] = {}

    @property
    def num_pairs(self) -> int:
        return len(self._pairs)

    @property
    def pairs(self) -> CandidatePairs:
        """The candidate pairs (a sequence of :class:`TrainPair`)."""
        return self._pairs

    def pair(self, k: int) -> TrainPair:
        """Candidate pair ``k``."""
        return self._pairs[k]

    def set_epoch(self, epoch: int) -> None:
        """Draw the pairs (with ``samples_per_epoch``), targets and replacements of another epoch."""
        self.epoch = int(epoch)
        self._perms.clear()

    def __len__(self) -> int:
        if self.config.per_scene is not None:
            return self.config.per_scene * self._pairs.num_scenes
        n = self.config.samples_per_epoch
        return self.num_pairs if n is None else int(n)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        sample, skipped = self.sample(i)
        for path, reason in skipped:
            self.record_skip(path, reason)
        return sample

    # -------------------------------------------------------------- internals
    def record_skip(self, path: str, reason: str) -> None:
        """Count one sample skipped because of ``path``; the first time, name it in a warning."""
        if path not in self.skipped:
            logger.warning("%s: unreadable image, skipped (%s)", path, reason)
        self.skipped[path] = self.skipped.get(path, 0) + 1

    def _all_images(self) -> set[str]:
        if self._images is None:
            self._images = {
                str(self.dataset.scenes[s].frames[int(j)].image)
                for s, frames in self._pairs.used_frames().items()
                for j in frames
            }
        return self._images

    def _pair_index(self, i: int) -> int:
        if self.config.per_scene is not None:
            return self._pairs.draw_by_scene(np.random.default_rng([_SCENE_TAG, self.seed, self.epoch % 2**63, i]))
        if self.config.samples_per_epoch is None:
            return i
        block, k = divmod(i, self.num_pairs)
        perm = self._perms.get((self.epoch, block))
        if perm is None:
            rng = np.random.default_rng([_PERM_TAG, self.seed, self.epoch % 2**63, block])
            perm = self._perms[(self.epoch, block)] = rng.permutation(self.num_pairs)
        return int(perm[k])

    def _draw_targets(self, rng: np.random.Generator, k: int) -> np.ndarray:
        cands = self._pairs.targets(k)
        T = self.config.targets
        if len(cands) >= T:
            return cands[rng.choice(len(cands), T, replace=False)]
        extra = cands[rng.choice(len(cands), T - len(cands), replace=True)]
        return np.concatenate([rng.permutation(cands), extra])

    def _view(self, scene: EvalScene, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        f = scene.frames[j]
        key = str(f.image)
        if key in self._bad:
            raise _Unreadable(key, self._bad[key])
        try:
            rgb = load_image(f.image).rgb
            if rgb.shape[:2] != (f.camera.height, f.camera.width):
                raise ImageReadError(
                    f"the image is {rgb.shape[1]}x{rgb.shape[0]}, its camera {f.camera.width}x{f.camera.height}"
                )
        except ImageReadError as e:
            self._bad[key] = str(e)
            raise _Unreadable(key, str(e)) from None
        K = np.array(f.camera.K, dtype=np.float64)
        x0, y0, x1, y1 = 0, 0, rgb.shape[1], rgb.shape[0]
        if self.config.crop == "principal-point":
            window = principal_point_window(K, f.camera.width, f.camera.height)
            if window is None:
                raise DatasetError(f"{key}: the principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) is on the image's "
                                   "border or outside it: no window centred on it to crop")  # fmt: skip
            x0, y0, x1, y1 = window
            K[0, 2] -= x0
            K[1, 2] -= y0
        img, K = resize_and_crop(rgb[y0:y1, x0:x1], K, self.config.size)
        d = None
        if self.depth:
            raw = scene.depth(j)
            W, H = self.config.size
            d = _crop_depth(raw[y0:y1, x0:x1], self.config.size) if raw is not None else np.zeros((H, W), np.float32)
        return img, K, d

    def sample(self, i: int) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
        """Sample ``i`` and the ``(file, reason)`` of each unreadable image that made a draw skip."""
        if not 0 <= i < len(self):
            raise IndexError(f"sample {i} out of range ({len(self)})")
        skipped: list[tuple[str, str]] = []
        for attempt in range(MAX_ATTEMPTS):
            rng = np.random.default_rng([_SAMPLE_TAG, self.seed, self.epoch % 2**63, i, attempt])
            k = self._pair_index(i) if attempt == 0 else int(rng.integers(self.num_pairs))
            targets = self._draw_targets(rng, k)
            scene = self.dataset.scenes[self._pairs.scene(k)]
            frames = [int(j) for j in (*self._pairs.context(k), *targets)]
            try:
                views = [self._view(scene, j) for j in frames]
            except _Unreadable as e:
                skipped.append((e.path, e.reason))
                if self._all_images().issubset(self._bad):
                    raise DatasetError(
                        f"{self.dataset.root}: every image of the training pairs is unreadable "
                        f"(e.g. {e.path}: {e.reason})"
                    ) from None
                continue
            imgs = torch.from_numpy(np.stack([v[0] for v in views])).permute(0, 3, 1, 2).contiguous()
            Ks = torch.from_numpy(np.stack([v[1] for v in views]))
            c2w = torch.from_numpy(np.stack([np.array(scene.frames[j].camera.cam_to_world) for j in frames]))
            out = {
                "context": imgs[:2],
                "context_K": Ks[:2],
                "context_c2w": c2w[:2],
                "target": imgs[2:],
                "target_K": Ks[2:],
                "target_c2w": c2w[2:],
                "index": torch.tensor(i, dtype=torch.int64),
            }
            if self.depth:
                ds = torch.from_numpy(np.stack([cast(np.ndarray, v[2]) for v in views]))  # self.depth: never None
                out["context_depth"], out["target_depth"] = ds[:2], ds[2:]
            return out, skipped
        raise DatasetError(
            f"{self.dataset.root}: no readable sample after {MAX_ATTEMPTS} draws for sample {i} "
            f"({len(self._bad)} unreadable image(s), e.g. {skipped[-1][0]})"
        )


# ------------------------------------------------------------------------------------ loader
class _Reporting(Dataset):
    """``PairDataset`` whose items carry the unreadable files, so the main process can count them."""

    def __init__(self, ds: PairDataset) -> None:
        self.ds = ds

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
        return self.ds.sample(i)


def _collate(
    items: list[tuple[dict[str, torch.Tensor], list[tuple[str, str]]]],
) -> tuple[dict[str, torch.Tensor], list[tuple[str, str]]]:
    return default_collate([s for s, _ in items]), [x for _, sk in items for x in sk]


def _seed_worker(worker_id: int) -> None:
    """Seed the global generators of a worker from its (deterministic) torch seed.

    (Not ``cv2.setNumThreads``: in a forked worker it can deadlock on the parent's thread pool.)
    """
    s = torch.initial_seed() % 2**32
    np.random.seed(s)
    random.seed(s)


class PairLoader(DataLoader):
    """A :class:`~torch.utils.data.DataLoader` of :class:`PairDataset` batches (:func:`make_loader`).

    Iterating yields the batches (dicts of tensors with a leading batch axis); unreadable files met by
    the workers are counted in ``pair_dataset.skipped`` and named once in a warning, in this process.

    Attributes:
        pair_dataset: the :class:`PairDataset` (``dataset`` is an internal wrapper of it).
    """

    pair_dataset: PairDataset

    def set_epoch(self, epoch: int) -> None:
        """Shuffle and draw for ``epoch`` (call before iterating; workers are started per epoch)."""
        self.pair_dataset.set_epoch(epoch)
        sampler = self.sampler.sampler if isinstance(self.sampler, _Skip) else self.sampler
        if isinstance(sampler, DistributedSampler):
            sampler.set_epoch(epoch)

    def __iter__(self) -> Any:
        for batch, skipped in super().__iter__():
            for path, reason in skipped:
                self.pair_dataset.record_skip(path, reason)
            yield batch


class _Skip(Sampler):
    """A sampler without its first ``start`` indices (a resumed epoch: what was done is not loaded again)."""

    def __init__(self, sampler: DistributedSampler, start: int) -> None:
        self.sampler, self.start = sampler, int(start)

    def __iter__(self) -> Iterator[int]:
        return itertools.islice(iter(self.sampler), self.start, None)

    def __len__(self) -> int:
        return max(0, len(self.sampler) - self.start)


def make_loader(
    ds: PairDataset,
    *,
    batch_size: int,
    workers: int = 0,
    shuffle: bool = True,
    seed: int = 0,
    rank: int = 0,
    world_size: int = 1,
    drop_last: bool = True,
    pin_memory: bool = False,
    start_batch: int = 0,
) -> PairLoader:
    """A deterministic loader of ``ds``: the same seed and epoch give the same batches, whatever ``workers``.

    The sampler is a :class:`~torch.utils.data.distributed.DistributedSampler` seeded with ``seed``
    (the same on every rank): rank ``r`` of ``world_size`` takes every ``world_size``-th index of one
    permutation of the epoch, so the ranks never overlap (with ``drop_last`` the tail that does not
    divide evenly is dropped; without, it is padded by repeating indices, as torch does). With
    ``world_size = 1`` it is a seeded shuffle. Call :meth:`PairLoader.set_epoch` before each epoch.

    Args:
        ds: the samples.
        batch_size: samples per batch (per rank).
        workers: worker processes (0: load in this process).
        shuffle: shuffle the samples of each epoch.
        seed: seed of the shuffle and of the workers' global generators.
        rank: this process's rank.
        world_size: number of processes.
        drop_last: drop the last incomplete batch (and the sampler's uneven tail).
        pin_memory: pin batches in page-locked memory (faster copies to a GPU).
        start_batch: begin the epoch at this batch (the samples before it are skipped, not loaded); the batches
            that follow are those of a loader that started at 0 (every sample's draw depends on its index only).

    Raises:
        InputError: a bad batch size, worker count, rank or start batch.
    """
    if batch_size < 1:
        raise InputError(f"batch size must be at least 1, got {batch_size}")
    if workers < 0:
        raise InputError(f"workers must be ≥ 0, got {workers}")
    if world_size < 1 or not 0 <= rank < world_size:
        raise InputError(f"rank {rank} is not in a world of {world_size}")
    if start_batch < 0:
        raise InputError(f"start batch must be ≥ 0, got {start_batch}")
    wrapped = _Reporting(ds)
    sampler: DistributedSampler[int] = DistributedSampler(
        wrapped, num_replicas=world_size, rank=rank, shuffle=shuffle, seed=int(seed), drop_last=drop_last
    )
    sampler.set_epoch(ds.epoch)
    order: Sampler = _Skip(sampler, start_batch * batch_size) if start_batch else sampler
    generator = torch.Generator()
    generator.manual_seed(int(seed) % 2**63)
    loader = PairLoader(
        wrapped,
        batch_size=batch_size,
        sampler=order,
        num_workers=workers,
        collate_fn=_collate,
        pin_memory=pin_memory,
        drop_last=drop_last,
        worker_init_fn=_seed_worker if workers > 0 else None,
        generator=generator,
        persistent_workers=False,
    )
    loader.pair_dataset = ds
    return loader
