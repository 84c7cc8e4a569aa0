"""SDP's model card carries its introduction, from LeRobot 0.6.1's policy method and from the free
`generate_model_card` of LeRobot's main branch."""

import sys
import types

import pytest
from huggingface_hub import ModelCard
from sdp_test_utils import tiny_config

from lerobot_sdp import model_card


@pytest.fixture(autouse=True)
def offline_validation(monkeypatch):
    """ModelCard.validate posts the card to the Hub; there is no Hub here."""
    monkeypatch.setattr(ModelCard, "validate", lambda self, *a, **k: None)


def test_lerobot_061_card_is_introduced_as_sdp():
    from lerobot_sdp import SDPPolicy

    card = SDPPolicy(tiny_config()).generate_model_card("local/pusht", "sdp", None, None)
    text = str(card)
    assert text.count(model_card.INTRODUCTION.strip()) == 1
    assert text.index("# Model Card for sdp") < text.index("Streaming Diffusion Policy (SDP)")


def main_branch_module(monkeypatch) -> types.ModuleType:
    """A stand-in for LeRobot main's `lerobot.common.train_utils`: its free function renders a card
    from the config alone, titled like LeRobot's template."""
    module = types.ModuleType(model_card.FREE_FUNCTION_MODULE)

    def generate_model_card(model_cfg, cfg=None, dataset_meta=None):
        return ModelCard(
            f"---\nlicense: apache-2.0\n---\n\n# Model Card for {model_cfg.type}\n\nLeRobot's text.\n"
        )

    module.generate_model_card = generate_model_card
    monkeypatch.setitem(sys.modules, model_card.FREE_FUNCTION_MODULE, module)
    return module


def test_main_branch_free_function_is_wrapped_for_sdp_only(monkeypatch):
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    module = main_branch_module(monkeypatch)
    assert model_card.install() and model_card.install()  # idempotent: wrapped once
    sdp = str(module.generate_model_card(tiny_config()))
    assert sdp.count(model_card.INTRODUCTION.strip()) == 1 and "LeRobot's text." in sdp
    dp = str(module.generate_model_card(DiffusionConfig()))
    assert model_card.INTRODUCTION.strip() not in dp and "# Model Card for diffusion" in dp


def test_lerobot_without_the_free_function_is_left_alone(monkeypatch):
    monkeypatch.setitem(sys.modules, model_card.FREE_FUNCTION_MODULE, types.ModuleType("empty"))
    assert not model_card.install()
