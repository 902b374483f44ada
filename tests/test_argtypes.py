"""ddp.argtypes: shared argparse types, and the scripts that use them refuse bad counts in one line."""

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from ddp.argtypes import positive_int

ROOT = Path(__file__).resolve().parents[1]


def test_positive_int_accepts_whole_numbers_from_one():
    assert positive_int("1") == 1
    assert positive_int("20") == 20


@pytest.mark.parametrize("text", ["0", "-3", "2.5", "ten", ""])
def test_positive_int_refuses_the_rest(text):
    with pytest.raises(argparse.ArgumentTypeError, match="whole number >= 1"):
        positive_int(text)


@pytest.mark.parametrize("script", ["metaworld_expert_report.py", "franka_oracle_report.py"])
def test_scripts_refuse_zero_episodes(script):
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / script), "--episodes", "0"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "--episodes: must be a whole number >= 1; got 0" in proc.stderr
    assert "Traceback" not in proc.stderr
