"""Declaring the locator's parameters on a node and reading them back as plain values."""
from __future__ import annotations

import array
import copy
from typing import Any

from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from vlp_ros.pipeline.config import ConfigError, LAMP_PARAMETERS, PARAMETERS, ParameterSpec

_STATIC_TYPES = {
    'string': Parameter.Type.STRING,
    'string_array': Parameter.Type.STRING_ARRAY,
    'integer': Parameter.Type.INTEGER,
    'bool': Parameter.Type.BOOL,
}
_INTEGER_RANGES = {'beacon.id_bits': (1, 16), 'qos.depth': (1, 1000)}
# Parameters every rclpy node may be given besides its own (qos_overrides.* are checked by check_qos_overrides).
_INFRASTRUCTURE = ('use_sim_time', 'start_type_description_service', 'qos_overrides.')
# The image subscription's policies that rclpy's QoSOverridingOptions.with_default_policies() reads.
_QOS_OVERRIDE_VALUES = {'reliability': ('reliable', 'best_effort', 'system_default'),
                        'history': ('keep_last', 'keep_all', 'system_default')}


def _descriptor(name: str, spec: ParameterSpec) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(name=name, description=spec.description, read_only=True)
    if spec.kind in ('number', 'number_array'):
        # Dynamic so that integers in a params file are accepted where doubles are meant.
        descriptor.dynamic_typing = True
    else:
        descriptor.type = _STATIC_TYPES[spec.kind].value
    if name in _INTEGER_RANGES:
        low, high = _INTEGER_RANGES[name]
        descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
    return descriptor


def _declare(node: Node, name: str, spec: ParameterSpec) -> Any:
    descriptor = _descriptor(name, spec)
    default = spec.default
    if default is None or default == []:
        # No value to infer a type from: declare the type (static) or nothing (dynamic).
        default = _STATIC_TYPES.get(spec.kind)
    try:
        value = node.declare_parameter(name, default, descriptor).value
    except (InvalidParameterTypeException, InvalidParameterValueException) as err:
        raise ConfigError(name, str(err).splitlines()[0]) from err
    if value is None:
        return copy.deepcopy(spec.default)
    return list(value) if isinstance(value, (tuple, array.array)) else value


def _redeclare(node: Node, name: str, spec: ParameterSpec) -> Any:
    if node.has_parameter(name):  # declared from an override, without our descriptor
        node.undeclare_parameter(name)
    return _declare(node, name, spec)


def declare_locator_parameters(node: Node) -> dict[str, Any]:
    """
    Declare every locator parameter (lamps as listed in leds.names) and return their values.

    The node must be built with ``automatically_declare_parameters_from_overrides=True``:
    rclpy lists the overrides it was given only as declared parameters. Each of ours is
    declared again with its descriptor (type, range, read-only), which checks the given
    value. Overrides that match none of ours are returned too when they look like lamp
    fields (so the validation can name a misspelt lamp) and rejected otherwise.
    """
    given = node.get_parameters_by_prefix('')
    values = {spec.name: _redeclare(node, spec.name, spec) for spec in PARAMETERS}
    for lamp in values['leds.names'] or []:
        for spec in LAMP_PARAMETERS:
            name = f'leds.{lamp}.{spec.name}'
            values[name] = _redeclare(node, name, spec)
    for name, parameter in given.items():
        if name in values or name.startswith(_INFRASTRUCTURE):
            continue
        if name.startswith('leds.'):
            values[name] = parameter.value
        else:
            raise ConfigError(name, 'unknown parameter (a typo?)')
    return values


def check_qos_overrides(node: Node, image_topic: str) -> None:
    """
    Check the ``qos_overrides.*`` parameters: only the image subscription's reliability, history and depth.

    rclpy applies them when the subscription is made (over ``qos.*``); any other one would be
    ignored silently, so it stops the node, as does a value rclpy would refuse.
    """
    prefix = f'qos_overrides.{image_topic}.subscription.'
    for name, parameter in node.get_parameters_by_prefix('qos_overrides').items():
        name = f'qos_overrides.{name}'
        policy = name[len(prefix):] if name.startswith(prefix) else None
        value = parameter.value
        if policy == 'depth':
            low, high = _INTEGER_RANGES['qos.depth']
            if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
                raise ConfigError(name, f'{value!r} is not a queue depth (an integer from {low} to {high})')
        elif policy in _QOS_OVERRIDE_VALUES:
            if not isinstance(value, str) or value.lower() not in _QOS_OVERRIDE_VALUES[policy]:
                raise ConfigError(name, f'{value!r} is none of {", ".join(_QOS_OVERRIDE_VALUES[policy])}')
        else:
            raise ConfigError(name, f'not used: the locator takes QoS overrides for its image subscription only '
                                    f'({prefix}reliability, history or depth)')
