"""The routers' Zenoh access control made from the roster (`tecdard fleet acl`): the same section serves
zenohd and `tecdard router`. Default deny; each rule names the certificates it is for.

A router sees each message where it enters (ingress, from the link it came on) and where it leaves
(egress, to the link it goes to); a link's subject is its peer's certificate's common name:
- a robot's daemon may publish, hold its token, declare its queryables and reply only under
  tecdar/<robot>/**, and is sent only the queries under tecdar/<robot>/cmd/** (and the declarations
  of whoever watches, so that it knows to publish);
- an operator may watch every robot (subscribe, liveliness) and query cmd/** only of the robots the
  roster gives it; it is sent those robots' queryables and replies, and what it watches;
- the routers of the roster pass everything under tecdar/ to each other: each router enforces the
  rules above at its own edge, where its robots and operators connect;
- nothing else, on any key: a client without a roster certificate gets nothing through."""
from __future__ import annotations

import json

from tecdard.fleet.roster import Roster

ROOT = "tecdar"
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query"]
WATCH_IN = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
WATCH_OUT = ["put", "delete", "liveliness_token", "reply"]


def _rule(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
            "key_exprs": list(key_exprs)}


def router_access_control(roster: Roster) -> dict:
    """The `access_control` section of every router of the fleet (zenoh 1.x ACL: rules, subjects,
    policies, default deny)."""
    everything = f"{ROOT}/**"
    rules = [_rule("watch-in", "ingress", WATCH_IN, [everything]),
             _rule("watch-out", "egress", WATCH_OUT, [everything])]
    subjects, policies = [], []
    if roster.routers:
        rules += [_rule("mesh-in", "ingress", ALL_MESSAGES, [everything]),
                  _rule("mesh-out", "egress", ALL_MESSAGES, [everything])]
        subjects.append({"id": "routers", "cert_common_names": list(roster.routers)})
        policies.append({"id": "routers", "rules": ["mesh-in", "mesh-out"], "subjects": ["routers"]})
    for robot in roster.robots:
        mine, cmd = f"{ROOT}/{robot}/**", f"{ROOT}/{robot}/cmd/**"
        rules += [_rule(f"robot-{robot}-out", "ingress", ["put", "delete", "liveliness_token", "declare_queryable",
                                                          "reply", "declare_subscriber"], [mine]),
                  _rule(f"robot-{robot}-in", "egress", ["query"], [cmd]),
                  _rule(f"robot-{robot}-watched", "egress", ["declare_subscriber", "declare_liveliness_subscriber"],
                        [everything])]
        subjects.append({"id": f"robot-{robot}", "cert_common_names": [robot]})
        policies.append({"id": f"robot-{robot}", "subjects": [f"robot-{robot}"],
                         "rules": [f"robot-{robot}-out", f"robot-{robot}-in", f"robot-{robot}-watched"]})
    for operator, robots in roster.operators.items():
        own = ["watch-in", "watch-out"]
        if robots:
            cmds = [f"{ROOT}/{r}/cmd/**" for r in robots]
            rules += [_rule(f"operator-{operator}-command", "ingress", ["query"], cmds),
                      _rule(f"operator-{operator}-served", "egress", ["declare_queryable", "reply"], cmds)]
            own += [f"operator-{operator}-command", f"operator-{operator}-served"]
        subjects.append({"id": f"operator-{operator}", "cert_common_names": [operator]})
        policies.append({"id": f"operator-{operator}", "rules": own, "subjects": [f"operator-{operator}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def acl_document(roster: Roster, source: str = "") -> str:
    """`tecdard fleet acl`'s output: a JSON5 config holding only the access_control section (JSON is
    JSON5), for zenohd's config (merged into it, or as `--config` with the endpoints and TLS beside it)
    and for `tecdard router` (access_control.file)."""
    head = "// tecdar fleet ACL, made by `tecdard fleet acl`" + (f" from {source}" if source else "") + "\n"
    return head + json.dumps({"access_control": router_access_control(roster)}, indent=2) + "\n"
