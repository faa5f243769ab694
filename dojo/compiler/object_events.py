"""Events a task writes on its objects instead of in `events:`: `hidden_after: <stage>` on an object entry.

`hidden_after` is sugar over the `hide` event (`dojo.backends.world_events`): the object (each copy of a counted
entry) is taken out of the scene the first step the named stage's condition holds, exactly as the event
`{when: <that stage's when>, hide: <object>}` would. The compiler appends these events after the spec's own, so
backends, routing (`plan.requires` names `events`) and the plan's program see one list of events.
"""

from __future__ import annotations

from typing import Any


def task_events(task: dict[str, Any]) -> list[dict[str, Any]]:
    """The task's `events:`, then one `hide` event per object copy that says `hidden_after` (stage names are
    checked when the spec is validated, `dojo.compiler.task_checks`)."""
    stages = {stage["name"]: stage["when"] for stage in task.get("stages", [])}
    events = list(task.get("events", []))
    for entry in task["scene"]["objects"]:
        stage = entry.get("hidden_after")
        if stage is None:
            continue
        count = entry.get("count", 1)
        names = [entry["name"]] if count == 1 else [f"{entry['name']}_{i}" for i in range(count)]
        events += [{"when": stages[stage], "hide": name} for name in names]
    return events
