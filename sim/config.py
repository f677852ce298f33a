"""The one way sim's config sections become frozen dataclasses (scene, camera, codec,
occlusion): unknown keys and values of the wrong type raise ValueError naming the key; each
dataclass's ``from_config`` adds the checks of its own ranges. Which sections each workflow
stage reads is :data:`STAGE_SECTIONS`."""

from __future__ import annotations

from dataclasses import fields
from typing import Any

# The config sections each stage reads: a stage re-runs only when its own sections change
# (a new tracking parameter does not re-render the video). The beam's geometry is in `beam`
# only, and the render stage reads it there too.
STAGE_SECTIONS: dict[str, list[str]] = {
    "sim": ["seed", "duration_s", "beam", "damping", "excitation", "sensor", "simulation"],
    "render": ["seed", "duration_s", "beam", "camera", "scene", "occlusion", "codec", "sensor"],
    "regions": ["seed", "beam", "camera", "scene", "occlusion", "sensor", "regions"],
}


def section_dataclass(cls, section: dict[str, Any], name: str):
    """Frozen dataclass from a config section; ValueError names unknown/bad keys."""
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise ValueError(f"{name}: unknown key(s) {', '.join(unknown)}; known: {', '.join(known)}")
    kwargs = {}
    for key, value in section.items():
        default = known[key].default
        if value is None or isinstance(default, str) or isinstance(value, str) and default is None:
            kwargs[key] = value
            continue
        try:
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise TypeError
                kwargs[key] = value
            elif isinstance(default, int) and not isinstance(default, bool):
                if float(value) != int(value):
                    raise TypeError
                kwargs[key] = int(value)
            elif isinstance(default, (tuple, list)):
                kwargs[key] = tuple(float(v) for v in value)
            else:
                kwargs[key] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name}.{key}: bad value {value!r} "
                             f"(expected {type(default).__name__})") from None
    return cls(**kwargs)
