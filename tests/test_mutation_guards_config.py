"""Guards found by mutation testing of the configuration (hsicam.config), the output helpers (hsicam.io), the memory
budget (hsicam.memory) and the device checks (hsicam.devices): each test kills a hand-made mutant (a bound moved by
one, a dropped check, a wrong key name, a skipped branch) that the rest of the suite let through. References are
independent of the code under test: the exact one-line error a user sees, values written out by hand, PyYAML's own
reading of a document, cgroup trees written here as the kernel lays them out.
"""

from __future__ import annotations

import re

import pytest

from hsicam.config import Config, identity_differences, load_config, training_differences
from hsicam.errors import ConfigError


def refused(overrides: list[str], message: str) -> None:
    """load_config with ``overrides`` over the defaults is a ConfigError whose text is exactly ``message``."""
    with pytest.raises(ConfigError) as exc:
        load_config(None, overrides)
    assert str(exc.value) == message


# --------------------------------------------------------------------------------------------
# config.py: YAML
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text", ["0x_", "0o_", "0x__", "0o__"])
def test_a_hex_or_octal_prefix_without_digits_is_a_config_error_not_a_traceback(text, tmp_path):
    """`seed: 0x_` matched the YAML 1.2 integer pattern (digits optional after the prefix) and PyYAML's int()
    raised a ValueError: a traceback from `hsicam train`, in a file or in --set alike."""
    refused([f"train.seed={text}"], f"config key 'train.seed' must be an integer, got '{text}'")
    path = tmp_path / "c.yaml"
    path.write_text(f"train:\n  seed: {text}\n")
    with pytest.raises(ConfigError) as exc:
        load_config(path)
    assert str(exc.value) == f"{path}: config key 'train.seed' must be an integer, got '{text}'"
