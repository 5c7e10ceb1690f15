"""The README, the docs and the example params file stay true to the code."""
from __future__ import annotations

import re

from conftest import ROOT

from vlp_ros.pipeline.config import LAMP_PARAMETERS, PARAMETERS, settings_from_params_file

import yaml


def test_parameter_reference_documents_every_parameter() -> None:
    reference = (ROOT / 'docs' / 'nodes.md').read_text()
    for spec in PARAMETERS:
        assert f'`{spec.name}`' in reference, spec.name
    for spec in LAMP_PARAMETERS:
        assert f'`leds.N.{spec.name}`' in reference, spec.name


def test_relative_links_lead_to_files() -> None:
    pages = [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]
    for page in pages:
        for target in re.findall(r'\]\(([^)#:]+)(?:#[^)]*)?\)', page.read_text()):
            assert (page.parent / target).exists(), f'{page.name} links to {target}'


def test_readme_quick_start_commands() -> None:
    readme = (ROOT / 'README.md').read_text()
    quick_start = readme.split('## Quick start', 1)[1].split('##', 1)[0]
    assert 'make demo' in quick_start and 'make test' in quick_start


def test_example_params_file_is_a_valid_locator_configuration() -> None:
    path = ROOT / 'config' / 'locator.example.yaml'
    settings = settings_from_params_file(path)
    names = yaml.safe_load(path.read_text())['vlp_locator']['ros__parameters']['leds']['names']
    assert sorted(lamp.name for lamp in settings.lamps) == sorted(names)
