"""The embedded synthetic sequence as a Dataset: rendered on demand, never read from disk."""

from __future__ import annotations

from pathlib import Path

from ti_fusion.camera import Intrinsics
from ti_fusion.config import DatasetConfig, SynthConfig
from ti_fusion.io.datasets.base import Dataset, Frame


class SyntheticDataset(Dataset):
    """Frames of ``ti_fusion.synthetic.scene.SyntheticSequence``, rendered lazily with ground-truth poses.

    Downsampling renders every f-th pixel directly (identical to subsampling the full render, at 1/f² of
    the cost). The renderer is created on first use and kept.
    """

    name = "synthetic"
    format = "synthetic"
    color_registered = True  # rendered: colour and depth from the same camera
    renders_on_taichi = True  # frames come from Taichi kernels: not read on a thread (io.prefetch)
    renders_in_process = True  # on the CPU backend, rendered in a reader process (io.prefetch.read_mode)

    def __init__(self, root: str | Path = "synthetic", config: DatasetConfig | None = None,
                 synth: SynthConfig | None = None, downsample: int = 1, start: int = 0,
                 stop: int | None = None, stride: int = 1):
        super().__init__(root, downsample=downsample, start=start, stop=stop, stride=stride)
        self.synth = synth or SynthConfig()
        self._sequence = None
        self.format_from = "no DATA given"
        self.intrinsics_source = "the synthetic camera (synth.fx, synth.width, synth.height)"

    @classmethod
    def from_config(cls, synth_cfg: SynthConfig, downsample: int = 1, start: int = 0,
                    stop: int | None = None, stride: int = 1) -> "SyntheticDataset":
        return cls("synthetic", synth=synth_cfg, downsample=downsample, start=start, stop=stop, stride=stride)

    def __getstate__(self) -> dict:
        """Pickled for a reader process without the sequence, which that process makes again."""
        state = dict(self.__dict__)
        state["_sequence"] = None
        return state

    @property
    def sequence(self):
        if self._sequence is None:
            from ti_fusion.synthetic.scene import SyntheticSequence

            self._sequence = SyntheticSequence(self.synth)
        return self._sequence

    @property
    def has_ground_truth(self) -> bool:
        return True

    @property
    def raw_intrinsics(self) -> Intrinsics:
        c = self.synth
        return Intrinsics(fx=c.fx, fy=c.fx, cx=(c.width - 1) / 2.0, cy=(c.height - 1) / 2.0,
                          width=c.width, height=c.height)

    def _num_raw_frames(self) -> int:
        return len(self.sequence)

    def _load_raw(self, raw_index: int) -> Frame:
        return self._render(raw_index, 1)

    def __getitem__(self, i: int) -> Frame:
        return self._render(self.indices[i], self.downsample)

    def _render(self, raw_index: int, downsample: int) -> Frame:
        seq = self.sequence
        depth, color = seq.frame(raw_index, downsample=downsample)
        return Frame(index=raw_index, timestamp=float(seq.timestamps[raw_index]), depth=depth,
                     intrinsics=seq.intrinsics.downsampled(downsample), color=color,
                     gt_pose=seq.poses[raw_index].copy(),
                     meta={"noise": self.synth.noise, "seed": self.synth.seed, "scene": self.synth.scene},
                     color_registered=True)

    def describe(self) -> dict:
        info = super().describe()
        info.update(noise=self.synth.noise, seed=self.synth.seed, scene=self.synth.scene)
        if self.synth.trajectory:
            info.update(trajectory=str(self.synth.trajectory))
        return info
