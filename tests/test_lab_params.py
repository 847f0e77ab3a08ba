"""``--param NAME=VALUE`` of the lab commands (``swarmloc experiment``, ``eval-pair``,
``honesty_study``): values reach the strict parameter models with their types."""

from __future__ import annotations

from client.lab.experiment_cli import param_value, parse_params
from service.estimators.registry import params_for


def test_values_are_typed_as_the_command_line_means_them() -> None:
    assert param_value("false") is False and param_value("True") is True
    assert param_value("3") == 3 and isinstance(param_value("3"), int)
    assert param_value("0.05") == 0.05
    assert param_value("paper") == "paper"


def test_a_switch_given_as_false_turns_it_off() -> None:
    """The strict DPSO model refuses the string 'false'; the parsed value is a bool."""
    p = params_for("dpso", parse_params(["metric_second=false", "v0=0.05"]))
    assert p.metric_second is False and p.v0 == 0.05  # type: ignore[attr-defined]
