"""Min-SNR-gamma loss weighting per slot (Hang et al., "Efficient Diffusion Training via Min-SNR
Weighting Strategy", ICCV 2023, arXiv 2303.09556, Eq. 6 and its epsilon form).

With SNR_t = abar_t / (1 - abar_t), the x0-prediction loss is weighted by min(SNR_t, gamma); written
for the network's target that is

- epsilon prediction: w_t = min(SNR_t, gamma) / SNR_t,
- sample prediction:  w_t = min(SNR_t, gamma).

Each slot of SDP's sequence has its own t, so each gets its own weight: the near-clean slots that the
chunk-wise scheme over-represents (SNR_t >> gamma) count for less. A clean slot (t = -1, abar = 1,
SNR = inf) gets weight 0 under epsilon prediction: its noise is not in the input.
"""

from torch import Tensor

from .schedule import PerSlotSchedule


def min_snr_weights(schedule: PerSlotSchedule, t: Tensor, gamma: float, prediction_type: str) -> Tensor:
    """(B, T, 1) loss weight of every slot at training timesteps ``t`` (B, T)."""
    abar = schedule.alpha_bar(t)
    snr = abar / (1 - abar)  # inf where abar = 1 (a clean slot)
    if prediction_type == "epsilon":
        return gamma / snr.clamp(min=gamma)  # min(SNR, gamma) / SNR, 0 at SNR = inf
    return snr.clamp(max=gamma)
