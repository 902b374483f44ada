"""scripts/detection_summary.py: one table of several `ddp detect` reports."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "detection_summary.py"


def test_the_summary_states_the_successful_episodes_false_alarms_where_tau_was_set_on_them(tmp_path):
    """tau set on successful ID episodes bounds their false alarms (alpha); the table printed only all
    episodes' count, which overstates what alpha bounds where the policy fails some ID episodes."""
    row = {"score": "point_newest", "threshold_on": "successful", "id_false_alarm_episodes": 5, "id_episodes": 20,
           "id_false_alarm_successful": 1, "id_successful": 14, "displace": {"detected_within_1": 17, "episodes": 20}}
    report = {"alpha": 0.05, "disturbances": ["displace"], "rows": [row, {**row, "score": "all_eps",
                                                                          "threshold_on": "all"}]}
    path = tmp_path / "pick" / "detect.json"
    path.parent.mkdir()
    path.write_text(json.dumps(report))
    out = subprocess.run([sys.executable, str(SCRIPT), str(path)], capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    assert lines[0] == "| score | pick / displace |"
    assert lines[2] == "| point_newest | 17/20 (5/20 FA, 1/14 successful) |"
    assert lines[3] == "| all_eps | 17/20 (5/20 FA) |"
