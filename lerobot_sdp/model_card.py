"""SDP's model card: LeRobot's card, introduced as SDP.

LeRobot's card template describes only LeRobot's own policies. In LeRobot 0.6.1 the card comes from
`PreTrainedPolicy.generate_model_card`, which `SDPPolicy` overrides with `add_introduction`. LeRobot's
main branch renders cards in a free function instead, `lerobot.common.train_utils.generate_model_card(
model_cfg, cfg, dataset_meta)` (used by `push_model_to_hub`, `lerobot-convert-dcp` and the normalisation
migration), where no policy method is called. `install()` wraps that function, where it exists, so that
the card of an `sdp` config gets the same introduction; every other policy's card is left as it is.
"""

import functools
import importlib

from huggingface_hub import ModelCard

POLICY_TYPE = "sdp"
INTRODUCTION = (
    "[Streaming Diffusion Policy (SDP)](https://arxiv.org/abs/2406.04806) keeps a buffer of partially "
    "denoised future actions at increasing noise levels, so every executed action chunk costs N/h denoiser "
    "calls instead of Diffusion Policy's N. Trained with the `lerobot_policy_sdp` plugin "
    "(`--policy.type=sdp`); install the plugin to load this model with LeRobot.\n"
)
FREE_FUNCTION_MODULE = "lerobot.common.train_utils"  # LeRobot's main branch (after 0.6.1)


def add_introduction(card: ModelCard) -> ModelCard:
    """Insert the SDP introduction under the title of an SDP card (once); other cards are unchanged."""
    title = f"# Model Card for {POLICY_TYPE}\n"
    if INTRODUCTION not in card.content:
        card.content = card.content.replace(title, title + "\n" + INTRODUCTION, 1)
    return card


def install() -> bool:
    """Wrap LeRobot's free `generate_model_card` when this LeRobot has one; True when it is wrapped."""
    try:
        module = importlib.import_module(FREE_FUNCTION_MODULE)
    except ImportError:  # LeRobot 0.6.1: the policy method renders the card
        return False
    generate = getattr(module, "generate_model_card", None)
    if generate is None:
        return False
    if getattr(generate, "_sdp_introduction", False):
        return True

    @functools.wraps(generate)
    def generate_model_card(model_cfg, *args, **kwargs):
        return add_introduction(generate(model_cfg, *args, **kwargs))

    generate_model_card._sdp_introduction = True
    module.generate_model_card = generate_model_card  # callers look it up in the module when they run
    return True
