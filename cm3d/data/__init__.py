"""Host-side data: sequences, the synthetic world, file formats."""

from cm3d.data.sequence import GroundTruth, Sequence

__all__ = ["GroundTruth", "Sequence"]
