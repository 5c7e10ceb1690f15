"""The README and the example params file stay true to the code."""
from __future__ import annotations

import yaml
from conftest import ROOT

from vlp_ros.locator_config import LAMP_PARAMETERS, PARAMETERS, default_parameters, settings_from_parameters


def _flatten(tree: dict, prefix: str = '') -> dict:
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f'{prefix}{key}.'))
        else:
            flat[prefix + key] = value
    return flat


def test_readme_documents_every_parameter() -> None:
    readme = (ROOT / 'README.md').read_text()
    for spec in PARAMETERS:
        assert f'`{spec.name}`' in readme, spec.name
    for spec in LAMP_PARAMETERS:
        assert f'`leds.N.{spec.name}`' in readme, spec.name


def test_readme_quick_start_commands() -> None:
    readme = (ROOT / 'README.md').read_text()
    quick_start = readme.split('## Quick start', 1)[1].split('##', 1)[0]
    assert 'make demo' in quick_start and 'make test' in quick_start


def test_example_params_file_is_a_valid_locator_configuration() -> None:
    params = yaml.safe_load((ROOT / 'config' / 'locator.example.yaml').read_text())
    values = default_parameters()
    values.update(_flatten(params['vlp_locator']['ros__parameters']))
    settings = settings_from_parameters(values)
    assert len(settings.lamps) == len(values['leds.names'])
