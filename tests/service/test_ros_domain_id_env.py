"""$ROS_DOMAIN_ID is checked as `--ros-domain-id` and `ros2.domain_id` are (0 to 232).

The setting's default comes from the environment, and pydantic does not check a default: with
ROS_DOMAIN_ID=300 (or -5) the service took domain 300, which the flag refuses, and with
ROS_DOMAIN_ID=abc it listened on domain 0 without a word, where the robots were not. Without
--ros2 the variable is not the service's, and a bad one stops nothing.
"""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.cli.main import main
from service.config import Settings


@pytest.mark.parametrize(("value", "domain"), [("7", 7), (" 12 ", 12), ("", 0), (None, 0)])
def test_a_valid_ros_domain_id_is_taken(
    monkeypatch: pytest.MonkeyPatch, value: str | None, domain: int
) -> None:
    if value is None:
        monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    else:
        monkeypatch.setenv("ROS_DOMAIN_ID", value)
    assert Settings().ros2.domain_id == domain


@pytest.mark.parametrize("value", ["300", "-5", "abc"])
def test_an_invalid_ros_domain_id_is_refused(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], value: str
) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    with pytest.raises(ValidationError):
        Settings(ros2={"enabled": True})
    assert main(["config", "--ros2"]) == 2
    err = capsys.readouterr().err
    assert "ROS_DOMAIN_ID" in err and "Traceback" not in err, err


def test_the_flag_overrides_an_invalid_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    assert main(["config", "--ros2", "--ros-domain-id", "3"]) == 0


def test_without_the_ros_front_door_the_variable_stops_nothing(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", "abc")
    assert Settings().ros2.domain_id == 0
    assert main(["config"]) == 0
