"""Whether NetworkPolicies let one pod open a TCP connection to another: the rules of the NetworkPolicy API
for the selectors the manifests use (matchLabels, matchExpressions with In, namespaceSelector on labels).

A connection is allowed when the destination's isolating policies admit it as ingress and the source's admit
it as egress; a pod that no policy of a direction selects is not isolated in that direction.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

Labels = dict[str, str]


@dataclass(frozen=True)
class Pod:
    namespace: str
    labels: Labels = field(default_factory=dict)
    namespace_labels: Labels = field(default_factory=dict)


def matches(selector: dict[str, Any] | None, labels: Labels) -> bool:
    if selector is None:
        return True
    if any(labels.get(key) != value for key, value in selector.get("matchLabels", {}).items()):
        return False
    for expression in selector.get("matchExpressions", []):
        if expression["operator"] != "In":
            raise NotImplementedError(expression["operator"])
        if labels.get(expression["key"]) not in expression["values"]:
            return False
    return True


def peer_matches(peer: dict[str, Any], other: Pod, policy_namespace: str) -> bool:
    if "ipBlock" in peer:
        raise NotImplementedError("ipBlock")
    if "namespaceSelector" in peer:
        if not matches(peer["namespaceSelector"], other.namespace_labels):
            return False
    elif other.namespace != policy_namespace:
        return False
    return matches(peer.get("podSelector"), other.labels)


def rule_admits(rule: dict[str, Any], peers_key: str, other: Pod, port: int, namespace: str) -> bool:
    ports = rule.get("ports")
    if ports is not None and not any(p.get("protocol", "TCP") == "TCP" and p.get("port") == port for p in ports):
        return False
    peers = rule.get(peers_key)
    return peers is None or any(peer_matches(peer, other, namespace) for peer in peers)


def admitted(policies: list[dict[str, Any]], pod: Pod, direction: str, other: Pod, port: int) -> bool:
    """Whether `pod`'s policies of `direction` ("Ingress" or "Egress") admit a connection with `other`."""
    isolating = [p for p in policies if p["metadata"]["namespace"] == pod.namespace
                 and direction in p["spec"].get("policyTypes", ["Ingress"])
                 and matches(p["spec"]["podSelector"], pod.labels)]
    if not isolating:
        return True
    rules_key, peers_key = ("ingress", "from") if direction == "Ingress" else ("egress", "to")
    return any(rule_admits(rule, peers_key, other, port, pod.namespace)
               for policy in isolating for rule in policy["spec"].get(rules_key) or [])


def can_connect(policies: list[dict[str, Any]], source: Pod, destination: Pod, port: int) -> bool:
    return (admitted(policies, destination, "Ingress", source, port)
            and admitted(policies, source, "Egress", destination, port))
