"""Access control on the bus: who may publish, subscribe and declare what (docs/security.md).

One table, :func:`roles`, says what each process of the stack does on the bus, in terms of the
catalogue's topics (:class:`~services.bus.messages.Keys`): which topics it publishes, which it
subscribes to, whether it watches or lists liveliness tokens, and under which service names it
declares its own liveliness token and ``ServiceStatus``. The role names are the stack's process
names (``configs/stack.toml``), ``viewer`` (``psm up --view`` adds it) plus ``operator``, the
command-line tools a person runs against a live stack (``psm status``, ``psm topics``,
``psm echo``, ``psm obstacle ...``, the supervisor's own session, a docker healthcheck).

:func:`acl_config` turns the table into zenoh's ``access_control`` configuration for the
router, default deny: each role is a subject (its user name for user/password authentication,
its certificate common name for TLS client certificates) with exactly the permissions its topics
need. What a topic needs, per zenoh message type and flow (seen from the router: *ingress* is
what a client sends, *egress* what the router forwards to it):

* publishing ``K``: ingress ``put`` on ``K``; a latched topic (an advanced publisher with a
  cache and publisher detection) also declares a queryable and a liveliness token on
  ``K/@adv/**`` and receives the history queries there (egress ``query``), and answers them
  (ingress ``reply`` on ``K``: a reply carries the cached sample's own key);
* subscribing to ``K``: ingress ``declare_subscriber`` and egress ``put`` on ``K``; a latched
  subscription (an advanced subscriber with history and late-publisher detection) also queries
  ``K/@adv/**`` (ingress ``query``; egress ``reply`` on ``K``) and watches the publishers'
  tokens there (ingress ``declare_liveliness_subscriber``, egress ``liveliness_token``).
  ``K/@adv/**`` needs its own rule: ``@adv`` is a verbatim chunk, which no wildcard
  (``psm/**``) matches;
* every role: egress ``declare_subscriber`` on ``<prefix>/**``. A zenoh publisher sends only
  while it knows of a matching subscriber; a role that may not learn of the subscribers drops
  every put itself, before the router could check and log it (and the recorder's ``<prefix>/**``
  subscription is what makes a topic without another subscriber reach the recording);
* its own health: ingress ``put`` on ``<prefix>/status/<service>``, ingress
  ``liveliness_token`` on ``<prefix>/alive/<service>``;
* watching liveliness (``Service.watch_liveliness``, the supervisor): ingress
  ``declare_liveliness_subscriber`` and egress ``liveliness_token`` on ``<prefix>/alive/*``;
  listing it (``psm status``): ingress ``liveliness_query`` and egress ``liveliness_token``.

Example::

    from services.bus.acl import acl_config, roles
    from services.bus.messages import Keys

    table = roles(Keys("psm"))
    assert any(t.key == "psm/arm/command" for t in table["planner"].publishes)
    conf = acl_config(Keys("psm"))          # the router's zenoh "access_control" value
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from services.bus.messages import Keys, Topic

__all__ = [
    "ACL_MESSAGES",
    "ADV_SUFFIX",
    "ROLE_NAMES",
    "Permission",
    "Role",
    "acl_config",
    "permissions",
    "role_services",
    "roles",
    "roles_markdown",
]

#: zenoh's ACL message types (``access_control.rules[].messages``).
ACL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
)

#: The roles, in the stack's start order; ``operator`` is a person's command-line tools.
ROLE_NAMES = ("recorder", "arm", "camera", "goal_tracker", "obstacle_monitor", "planner", "viewer",
              "operator")

#: The ``psm`` command(s) each role runs: their liveliness / status names come from the stack's
#: command registry (:data:`services.stack.COMMANDS`), e.g. the camera's ``camera_synth``.
_ROLE_COMMANDS: dict[str, tuple[tuple[str, ...], ...]] = {
    "recorder": (("record",),),
    "arm": (("arm",),),
    "camera": (("camera", "synth"),),
    "goal_tracker": (("track",),),
    "obstacle_monitor": (("obstacles",),),
    "planner": (("plan",),),
    "viewer": (("view",),),
    "operator": (("echo",),),
}

#: The suffix under which zenoh's advanced publishers and subscribers keep their cache
#: queryables, liveliness tokens and history queries (``<key>/@adv/...``).
ADV_SUFFIX = "@adv/**"


@dataclass(frozen=True)
class Role:
    """What one process does on the bus (see the module docstring)."""

    name: str
    what: str
    services: tuple[str, ...]
    publishes: tuple[Topic, ...] = ()
    subscribes: tuple[Topic, ...] = ()
    watches_liveliness: bool = False
    lists_liveliness: bool = False


@dataclass(frozen=True, order=True)
class Permission:
    """One allowed (flow, message, key expression) of a role."""

    flow: str  # "ingress" (from the client) or "egress" (to the client)
    message: str  # one of ACL_MESSAGES
    key: str


def role_services(role: str) -> tuple[str, ...]:
    """The liveliness / status names the processes of ``role`` declare."""
    from services.stack import COMMANDS

    return tuple(COMMANDS[c].service or c[0] for c in _ROLE_COMMANDS[role])


def roles(keys: Keys) -> dict[str, Role]:
    """The roles table of the cell ``keys`` (read from each service's code: its publishers,
    subscriptions and liveliness watches)."""
    k = keys
    table = [
        Role(
            "recorder", "psm record: every sample of the cell to MCAP, latched history included",
            role_services("recorder"),
            subscribes=(k.all, *k.latched_selectors()),
        ),
        Role(
            "arm", "psm arm: steps on the commands, publishes its state; brakes on a watched "
            "service's loss",
            role_services("arm"),
            publishes=(k.arm_state, k.arm_transforms, k.arm_model),
            subscribes=(k.arm_command,),
            watches_liveliness=True,
        ),
        Role(
            "camera", "psm camera synth: frames (times from the arm's state)",
            role_services("camera"),
            publishes=(k.camera_images_all,),
            subscribes=(k.arm_state,),
        ),
        Role(
            "goal_tracker", "psm track: frames (a topic, or its own camera) to the person's goal",
            role_services("goal_tracker"),
            publishes=(k.vision_faces, k.goals_all, k.viz_goals_all, k.camera_images_all,
                       k.camera_annotations_all),
            subscribes=(k.camera_images_all, k.arm_state),
        ),
        Role(
            "obstacle_monitor", "psm obstacles: the obstacle set, a collision prediction per "
            "state",
            role_services("obstacle_monitor"),
            publishes=(k.collision, k.obstacles, k.scene),
            subscribes=(k.arm_state, k.planner_goal, k.obstacles_command),
        ),
        Role(
            "planner", "psm plan: the task; the only role that commands the arm",
            role_services("planner"),
            publishes=(k.arm_command, k.planner_status, k.task_events, k.gripper_command,
                       k.planner_goal, k.viz_plan),
            subscribes=(k.arm_state, k.goals_all, k.collision),
            watches_liveliness=True,
        ),
        Role(
            "viewer", "psm view (psm up --view): the cell to Foxglove, latched history "
            "included; reads only",
            role_services("viewer"),
            subscribes=(k.all, *k.latched_selectors()),
        ),
        Role(
            "operator", "a person's tools: psm status / topics / echo, psm obstacle, the "
            "supervisor's session, a healthcheck: reads everything, changes obstacles, never "
            "commands the arm",
            role_services("operator"),
            publishes=(k.obstacles_command,),
            subscribes=(k.all,),
            watches_liveliness=True,
            lists_liveliness=True,
        ),
    ]
    out = {r.name: r for r in table}
    assert tuple(out) == ROLE_NAMES
    return out


def _adv(topic: Topic) -> str:
    """The key expression of a latched topic's advanced pub/sub traffic."""
    return f"{topic.key}/{ADV_SUFFIX}"


def permissions(role: Role, keys: Keys) -> list[Permission]:
    """Everything ``role`` is allowed, sorted (see the module docstring for why each)."""
    out: set[Permission] = {Permission("egress", "declare_subscriber", keys.all.key)}

    def add(flow: str, messages: Iterable[str], key: str) -> None:
        out.update(Permission(flow, m, key) for m in messages)

    for name in role.services:
        add("ingress", ["put"], keys.status(name).key)
        add("ingress", ["liveliness_token"], keys.liveliness(name).key)
    for t in role.publishes:
        add("ingress", ["put"], t.key)
        if t.qos.history > 0:
            add("ingress", ["declare_queryable", "liveliness_token"], _adv(t))
            add("egress", ["query"], _adv(t))
            add("ingress", ["reply"], t.key)  # a reply carries the cached sample's own key
    for t in role.subscribes:
        add("ingress", ["declare_subscriber"], t.key)
        add("egress", ["put"], t.key)
        if t.qos.history > 0:
            add("ingress", ["query", "declare_liveliness_subscriber"], _adv(t))
            add("egress", ["liveliness_token"], _adv(t))
            add("egress", ["reply"], t.key)
    alive = keys.liveliness_all.key
    if role.watches_liveliness:
        add("ingress", ["declare_liveliness_subscriber"], alive)
        add("egress", ["liveliness_token"], alive)
    if role.lists_liveliness:
        add("ingress", ["liveliness_query"], alive)
        add("egress", ["liveliness_token"], alive)
    return sorted(out)


def _rules_of(role: Role, keys: Keys) -> Iterator[dict[str, object]]:
    """zenoh rules allowing exactly :func:`permissions`: one rule per (flow, key set) with
    the messages that share it."""
    by_message: dict[tuple[str, str], list[str]] = {}
    for p in permissions(role, keys):
        by_message.setdefault((p.flow, p.message), []).append(p.key)
    grouped: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for (flow, message), key_list in by_message.items():
        grouped.setdefault((flow, tuple(sorted(key_list))), []).append(message)
    for i, ((flow, key_list), messages) in enumerate(sorted(grouped.items())):
        yield {
            "id": f"{role.name}-{i}",
            "messages": sorted(messages, key=ACL_MESSAGES.index),
            "flows": [flow],
            "permission": "allow",
            "key_exprs": list(key_list),
        }


def acl_config(keys: Keys, role_names: Iterable[str] = ROLE_NAMES) -> dict[str, object]:
    """zenoh's ``access_control`` configuration for the roles ``role_names`` of the cell:
    enabled, default deny, each role a subject identified by its user name (user/password
    authentication) or by its TLS client certificate's common name, allowed exactly its
    :func:`permissions`."""
    table = roles(keys)
    rules: list[dict[str, object]] = []
    subjects: list[dict[str, object]] = []
    policies: list[dict[str, object]] = []
    for name in role_names:
        role_rules = list(_rules_of(table[name], keys))
        rules.extend(role_rules)
        subjects.append({"id": f"{name}-user", "usernames": [name]})
        subjects.append({"id": f"{name}-cert", "cert_common_names": [name]})
        policies.append({
            "id": name,
            "rules": [r["id"] for r in role_rules],
            "subjects": [f"{name}-user", f"{name}-cert"],
        })
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def roles_markdown(keys: Keys) -> str:
    """The roles table as markdown (docs/security.md shows it; a test keeps them equal)."""
    lines = [
        "| role | what | publishes | subscribes to | liveliness |",
        "|---|---|---|---|---|",
    ]

    def keys_of(topics: tuple[Topic, ...]) -> str:
        return ", ".join(
            f"`{t.key}`" + (" (latched)" if t.qos.history > 0 else "") for t in topics
        ) or "—"

    for role in roles(keys).values():
        live = [f"token `{keys.liveliness(s).key}`, status `{keys.status(s).key}`"
                for s in role.services]
        if role.watches_liveliness:
            live.append("watches `" + keys.liveliness_all.key + "`")
        if role.lists_liveliness:
            live.append("lists `" + keys.liveliness_all.key + "`")
        lines.append(
            f"| `{role.name}` | {role.what} | {keys_of(role.publishes)} | "
            f"{keys_of(role.subscribes)} | {'; '.join(live)} |"
        )
    return "\n".join(lines) + "\n"
