"""The client follows the service: every operation of the service's registry
(``service.operations.OPERATIONS``) has a row in the client's table
(:data:`ffs.operations.OPERATIONS`), a :class:`~ffs.client.Client` method and request
builder, a :class:`~ffs.local.Local` method with the client's arguments, a result type, and
an ``ffs`` command with a runner. Adding an operation to the service fails here until the
client, the in-process backend and the command line have it."""

from __future__ import annotations

import inspect

import pytest

from ffs import results
from ffs.cli.arguments import build_parser
from ffs.cli.commands import RUNNERS
from ffs.client import Client
from ffs.local import Local
from ffs.operations import COMMANDS, OPERATIONS
from service.operations import OPERATIONS as SERVICE_OPERATIONS


def subcommands() -> set[str]:
    parser = build_parser()
    action = next(a for a in parser._actions if a.dest == "command")
    return set(action.choices)


def test_the_table_lists_exactly_the_service_operations():
    assert list(OPERATIONS) == list(SERVICE_OPERATIONS)


@pytest.mark.parametrize("name", list(SERVICE_OPERATIONS))
def test_every_service_operation_has_a_method_a_local_call_and_a_command(name):
    operation = OPERATIONS[name]
    method = getattr(Client, operation.method)
    build = getattr(Client, f"{operation.method}_call")
    local = getattr(Local, operation.method)
    assert issubclass(getattr(results, operation.result), object)
    assert callable(getattr(results, operation.result).from_dict)
    # the local call takes what the client's method takes (arguments, keywords, progress)
    client_args = [p.name for p in inspect.signature(method).parameters.values()
                   if p.kind is not p.VAR_KEYWORD]
    local_args = [p.name for p in inspect.signature(local).parameters.values()
                  if p.kind is not p.VAR_KEYWORD]
    assert set(client_args) <= set(local_args) | {"self"}, (client_args, local_args)
    assert "progress" in client_args and method.__doc__ == build.__doc__
    commands = [c.name for c in COMMANDS.values() if name in c.operations]
    assert commands, f"no ffs command runs {name}"
    assert set(commands) <= subcommands() and set(commands) <= set(RUNNERS)


def test_every_command_has_a_parser_and_a_runner():
    assert set(COMMANDS) == set(RUNNERS) == subcommands() - {"serve"}
    for command in COMMANDS.values():
        assert set(command.operations) <= set(OPERATIONS), command


def test_submit_takes_every_operation():
    assert set(Client.CALLS) == set(SERVICE_OPERATIONS)


@pytest.mark.parametrize("name", [n for n, op in OPERATIONS.items() if op.arrays])
def test_requests_made_from_the_table_match_the_service(name):
    """A request built from its row: the service's arrays, in its order; options only where
    the service's params have them."""
    import numpy as np

    operation, spec = OPERATIONS[name], SERVICE_OPERATIONS[name]
    assert list(operation.arrays) == list(spec.arrays)
    assert operation.options == ("options" in spec.params.model_fields)
    client = Client.__new__(Client)  # no connection: only the request is built
    arrays = [np.full((2, 3), k) for k in range(len(operation.arrays))]
    call = getattr(client, f"{operation.method}_call")(*arrays)
    assert call.operation == name and list(call.arrays) == list(spec.arrays)
    for k, array in enumerate(call.arrays.values()):
        np.testing.assert_array_equal(array, arrays[k])
    assert call.params == ({"options": {}} if operation.options else {})
    if operation.options:
        call = getattr(client, f"{operation.method}_call")(*arrays, refine=False, seams="none")
        assert call.params == {"options": {"refine": False, "seams": "none"}}
    else:
        with pytest.raises(TypeError):
            getattr(client, f"{operation.method}_call")(*arrays, refine=False)
