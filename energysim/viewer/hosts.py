"""Which ``Host`` a request may name: the viewer answers only requests addressed to itself.

A web page on another site can point its own DNS name at 127.0.0.1 ("DNS rebinding") and then read
the viewer's responses as if they were its own origin. The browser still sends that site's name in
the ``Host`` header, so a server that answers only the names it is known by is out of its reach.

A request is accepted when its ``Host`` names

* a loopback name: ``localhost``, ``127.0.0.1`` or ``[::1]``;
* the host the server was told to bind (as given, and the address it resolved to), unless that is
  a wildcard (``0.0.0.0``, ``::``, ``""``), which names no one;
* the IP address the connection arrived on. An IP-literal ``Host`` cannot come from a rebound DNS
  name: the page's origin is then that address itself, which is this server. This is what lets
  other machines reach a server bound to all interfaces by its address;
* a name listed in ``allowed_hosts`` (e.g. the machine's DNS name when it serves other machines).

and its port, when it gives one, is the port served (an ``allowed_hosts`` entry ``name:port`` allows
that name at that other port, e.g. the local end of a tunnel). ``Host`` without a port is accepted.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass

__all__ = ["LOOPBACK_NAMES", "WILDCARD_ADDRESSES", "HostAllowList", "split_authority"]

LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
WILDCARD_ADDRESSES = ("", "0.0.0.0", "::")

# Characters that never occur in a host name or an IP literal; an entry containing one is a mistake
# (a URL, a path, user info) rather than a name.
_NOT_IN_A_NAME = frozenset(" \t\r\n/\\@?#[]")


def canonical_name(name: str) -> str:
    """`name` lower-cased; an IP address in canonical form, an IPv4-mapped IPv6 address as IPv4."""
    try:
        address = ipaddress.ip_address(name)
    except ValueError:
        return name.lower()
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(address)


def split_authority(text: str) -> tuple[str, int | None]:
    """``(name, port)`` of a ``Host`` value: ``name``, ``name:port``, ``[v6]``, ``[v6]:port`` or a bare IPv6.

    The name is canonical (see `canonical_name`); the port is None when absent or empty. Raises
    ValueError for anything else (an unclosed bracket, a port that is not 0-65535, characters that
    cannot be in a host name).
    """
    value = text.strip()
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            raise ValueError(f"host {text!r} opens '[' and never closes it")
        name, rest = value[1:end], value[end + 1 :]
        try:
            ipaddress.IPv6Address(name)
        except ValueError as err:
            raise ValueError(f"host {text!r}: {name!r} in brackets is not an IPv6 address") from err
    elif value.count(":") > 1:
        name, rest = value, ""  # a bare IPv6 address; checked below
        try:
            ipaddress.IPv6Address(name)
        except ValueError as err:
            raise ValueError(f"host {text!r} has several ':' but is not an IPv6 address") from err
    else:
        name, colon, port_text = value.partition(":")
        rest = colon + port_text
    if not name or any(c in _NOT_IN_A_NAME or not c.isprintable() for c in name.strip("[]")):
        raise ValueError(f"host {text!r} does not name a host")
    if rest in ("", ":"):
        return canonical_name(name), None
    digits = rest[1:]
    if not rest.startswith(":") or not (digits.isascii() and digits.isdigit()) or int(digits) > 65535:
        raise ValueError(f"host {text!r}: port {digits!r} must be an integer in [0, 65535]")
    return canonical_name(name), int(digits)


@dataclass(frozen=True)
class HostAllowList:
    """The ``Host`` values one server answers (rules in the module docstring).

    Attributes:
        port: the TCP port served; a ``Host`` that names a port must name this one.
        names: canonical names accepted at `port` or without a port.
        name_ports: ``(name, port)`` pairs accepted at a port other than `port`.
    """

    port: int
    names: frozenset[str]
    name_ports: frozenset[tuple[str, int]]

    @classmethod
    def build(
        cls, bound_host: str, bound_address: str, port: int, allowed_hosts: Iterable[str]
    ) -> HostAllowList:
        """The allow-list of a server bound to `bound_host`, which resolved to `bound_address`, at `port`.

        Raises ValueError naming an `allowed_hosts` entry that is not ``name`` or ``name:port``, and
        TypeError for an entry that is not a string (or for a bare string given instead of a list).
        """
        if isinstance(allowed_hosts, str):
            raise TypeError(f"allowed_hosts must be a list of host names, got the string {allowed_hosts!r}")
        names = {canonical_name(n) for n in LOOPBACK_NAMES}
        for bound in (bound_host, bound_address):
            if bound not in WILDCARD_ADDRESSES:
                names.add(canonical_name(bound.strip("[]")))
        name_ports = set()
        for entry in allowed_hosts:
            if not isinstance(entry, str):
                raise TypeError(f"allowed_hosts entries must be strings, got {entry!r}")
            try:
                name, entry_port = split_authority(entry)
            except ValueError as err:
                raise ValueError(
                    f"allowed_hosts entry {entry!r} is not 'name' or 'name:port': {err}"
                ) from err
            if entry_port is None or entry_port == port:
                names.add(name)
            else:
                name_ports.add((name, entry_port))
        return cls(port, frozenset(names), frozenset(name_ports))

    def allows(self, host: str, local_address: str | None = None) -> bool:
        """Whether a request with ``Host: host`` that arrived on `local_address` is addressed here."""
        try:
            name, port = split_authority(host)
        except ValueError:
            return False
        if port is not None and port != self.port:
            return (name, port) in self.name_ports
        if name in self.names:
            return True
        return local_address is not None and name == canonical_name(local_address)
