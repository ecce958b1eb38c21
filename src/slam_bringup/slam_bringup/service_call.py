"""slam_call: call a service and print the response as YAML, like `ros2 service call`.

Example: slam_call find_landmark '{landmark_id: 7}' (a unique tail of the name works).
Exit status: 0; 1 a false `success` or `found`; 2 a usage error, an unknown service or a
request that does not fit; 3 no response within --timeout."""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

from slam_core.cli import PlainDescriptionHelpFormatter, console_main, positive_float
from slam_core.errors import SlamError

EXIT_FALSE = 1
EXIT_NO_RESPONSE = 3
OUTCOME_FIELDS = ('success', 'found')


def build_parser() -> argparse.ArgumentParser:
    """The command line of slam_call."""
    parser = argparse.ArgumentParser(
        prog='slam_call', description=__doc__, formatter_class=PlainDescriptionHelpFormatter
    )
    add = parser.add_argument
    add('service', help='service name, e.g. /em_sam_mapper/optimize (a unique tail works)')
    add('request', nargs='?', default='{}', help="the request as YAML, e.g. '{landmark_id: 7}'")
    add('--type', help='service type, e.g. std_srvs/srv/Trigger (default: from the graph)')
    add(
        '--wait',
        type=positive_float,
        default=5.0,
        metavar='S',
        help='wait S s for the service to appear',
    )
    add(
        '--timeout',
        type=positive_float,
        default=60.0,
        metavar='S',
        help='wait S s for the response',
    )
    return parser


def parse_request(text: str) -> object:
    """The request YAML as data; SlamError when it is not YAML."""
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise SlamError(f'the request {text!r} is not YAML: {err}') from None


def outcome(response: dict[str, Any]) -> int:
    """1 when a success/found field of ``response`` is false, else 0."""
    return EXIT_FALSE if any(response.get(key) is False for key in OUTCOME_FIELDS) else 0


@console_main('slam_call')
def main(argv: list[str] | None = None) -> int:
    """Call one service once."""
    args = build_parser().parse_args(sys.argv[1:] if argv is None else argv)
    values = parse_request(args.request)
    from slam_bringup.graph_lookup import Found, RosSession, find_service
    from slam_bringup.message_yaml import fill_message, message_to_data, to_yaml
    from slam_ros.typesys import message_class

    with RosSession('slam_call') as ros:
        if args.type:
            found = Found('/' + args.service.lstrip('/'), args.type)
        else:
            found = find_service(ros.node, args.service, args.wait)
        service_type: Any = message_class(found.type_name)
        request = fill_message(service_type.Request(), values)
        client = ros.node.create_client(service_type, found.name)
        deadline = time.monotonic() + args.wait
        while not client.service_is_ready():
            if time.monotonic() > deadline or not ros.spin_once(0.05):
                raise SlamError(f'service {found.name} ({found.type_name}) is not ready')
        print(f'calling {found.name} ({found.type_name})', file=sys.stderr)  # noqa: T201
        future = client.call_async(request)
        deadline = time.monotonic() + args.timeout
        while not future.done():
            if not ros.spin_once(0.05):
                raise KeyboardInterrupt  # Ctrl-C: console_main exits 130
            if time.monotonic() > deadline:
                print(  # noqa: T201
                    f'slam_call: error: no response from {found.name} within {args.timeout:g} s',
                    file=sys.stderr,
                )
                return EXIT_NO_RESPONSE
        response = future.result()
    data = message_to_data(response, truncate=None)
    sys.stdout.write(to_yaml(data))
    return outcome(data)


if __name__ == '__main__':
    sys.exit(main())
