"""A glTF scene's camera and lights as Mitsuba's sensor and emitters.

:func:`scene_sensor` is the file's first camera (perspective or orthographic; its aspect ratio sets
the image's width) or, without one, a camera that frames the model's bounding box;
:func:`scene_emitters` are the file's ``KHR_lights_punctual`` lights (directional, point, spot) or,
without them, a generated sky with a sun. A degenerate node transform (a zero scale, an
overflow) skips that camera or light with a warning.
"""

from __future__ import annotations

import math

import numpy as np

from mfnormal.io.gltf_arrays import warn
from mfnormal.io.gltf_validate import GLTFError
from mfnormal.io.inputs import Limits
from mfnormal.scenes import sky

def _look_at(origin, target, up):
    import mitsuba as mi

    return mi.ScalarTransform4f().look_at(origin=[float(x) for x in origin],
                                          target=[float(x) for x in target], up=[float(x) for x in up])


def _axis(world, v):
    """The unit world-space direction of the node-space vector ``v``, or None if degenerate."""
    d = world[:3, :3] @ np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(d))
    return d / n if np.isfinite(n) and n > 1e-12 * max(1.0, float(np.abs(world[:3, :3]).max())) else None


def gltf_camera(cam, world):
    """A Mitsuba sensor (without sampler and film) from a glTF camera at ``world``, or None
    where the node's transform is degenerate (a zero scale, an overflow)."""
    import mitsuba as mi

    # glTF cameras look down −Z with +X right; Mitsuba's look down +Z with +X left.
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    if not np.all(np.isfinite(world)) or any(_axis(world, e) is None for e in np.eye(3)):
        return None
    rot = world.copy()
    rot[:3, :3] /= np.linalg.norm(rot[:3, :3], axis=0, keepdims=True)   # drop scale
    if abs(np.linalg.det(rot[:3, :3])) < 1e-6:
        return None
    to_world = mi.ScalarTransform4f((rot @ flip).tolist())
    if cam.type == "orthographic":
        o = cam.orthographic
        return {"type": "orthographic",
                "to_world": to_world @ mi.ScalarTransform4f().scale([o.xmag, o.ymag, 1.0])}
    p = cam.perspective
    near = float(p.znear)
    return {"type": "perspective", "fov_axis": "y",
            "fov": min(max(math.degrees(p.yfov), 1e-4), 179.9),    # validated in (0°, 180°)
            "near_clip": near, "far_clip": max(1e4, 1e3 * near), "to_world": to_world}


def framing_camera(lo, hi, aspect, fov=35.0, elevation=20.0, azimuth=20.0, margin=1.1):
    """A perspective sensor that frames the box [lo, hi] from the front (+Z), a little above:
    the box's corners fill the smaller image side (with ``margin``)."""
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    el, az = math.radians(elevation), math.radians(azimuth)
    back = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - center
    tan_half_y = math.tan(math.radians(0.5 * fov)) / min(1.0, aspect)   # fov spans the smaller side
    tan_y = tan_half_y / margin
    tan_x = tan_y * aspect
    # Distance along ``back`` at which every corner projects inside the image.
    depth = corners @ back
    distance = float(np.max(np.maximum(np.abs(corners @ right) / tan_x,
                                       np.abs(corners @ up) / tan_y) + depth))
    distance = max(distance, 1e-3 * radius)
    return {"type": "perspective", "fov_axis": "y", "fov": 2 * math.degrees(math.atan(tan_half_y)),
            "near_clip": max(distance - 2 * radius, distance * 1e-3),
            "far_clip": distance + 4 * radius,
            "to_world": _look_at(center + distance * back, center, [0, 1, 0])}


def punctual_lights(gltf, nodes):
    """Mitsuba emitters for the KHR_lights_punctual lights of the scene's nodes (validated:
    known types, indices in range, colours and intensities >= 0, cone angles in order)."""
    ext = (gltf.extensions or {}).get("KHR_lights_punctual", {})
    lights = ext.get("lights", [])
    emitters = {}
    for i, node, world in nodes:
        ref = (node.extensions or {}).get("KHR_lights_punctual")
        if ref is None:
            continue
        light = lights[ref["light"]]
        colour = np.array(light.get("color", [1, 1, 1]), dtype=np.float64) * light.get("intensity", 1.0)
        rgb = {"type": "rgb", "value": colour.tolist()}
        position = world[:3, 3]
        direction, up = _axis(world, [0.0, 0.0, -1.0]), _axis(world, [0.0, 1.0, 0.0])
        kind = light.get("type")
        if not np.all(np.isfinite(position)) or (kind != "point" and (direction is None or up is None)):
            warn(f"nodes[{i}]: the transform of its light is degenerate (a zero scale or an "
                 "overflow); the light is skipped")
            continue
        name = f"light_{len(emitters)}"
        if kind == "directional":
            emitters[name] = {"type": "directional", "direction": direction.tolist(), "irradiance": rgb}
        elif kind == "point":
            emitters[name] = {"type": "point", "position": position.tolist(), "intensity": rgb}
        elif kind == "spot":
            spot = light.get("spot", {})
            emitters[name] = {"type": "spot", "intensity": rgb,
                              "cutoff_angle": math.degrees(spot.get("outerConeAngle", math.pi / 4)),
                              "beam_width": math.degrees(spot.get("innerConeAngle", 0.0)),
                              "to_world": _look_at(position, position + direction, up)}
    return emitters


def scene_sensor(gltf, nodes, lo, hi, width: int, height: int, spp: int, limits: Limits) -> dict:
    """The file's first camera (its aspect ratio sets the width), else one that frames the
    box [lo, hi]; with sampler and film."""
    sensor = None
    for i, node, world in nodes:
        if node.camera is not None:
            cam = gltf.cameras[node.camera]
            sensor = gltf_camera(cam, world)
            if sensor is None:
                warn(f"nodes[{i}]: the transform of its camera is degenerate (a zero scale or an "
                     "overflow); using a camera that frames the model")
                break
            aspect = cam.perspective.aspectRatio if cam.type == "perspective" else None
            if aspect:
                width = max(1, int(round(height * aspect)))
                check_render_size(width, height, limits, f"cameras[{node.camera}].perspective.aspectRatio "
                                                         f"{aspect:g} at height {height}")
            break
    if sensor is None:
        sensor = framing_camera(lo, hi, width / height)
    sensor["sampler"] = {"type": "independent", "sample_count": int(spp)}
    sensor["film"] = {"type": "hdrfilm", "width": int(width), "height": int(height),
                      "pixel_format": "rgb", "rfilter": {"type": "gaussian"}}
    return sensor


def scene_emitters(gltf, nodes, lights: bool) -> dict:
    """The file's punctual lights (unless ``lights`` is False), else a generated sky with a sun."""
    import mitsuba as mi

    emitters = punctual_lights(gltf, nodes) if lights else {}
    if not emitters:
        sun = sky.DiskSun(elevation_deg=40.0, azimuth_deg=-35.0, irradiance=3.0, radius_deg=3.0)
        bitmap = mi.Bitmap(sky.envmap(256, gradient=sky.GLTF, sun=sun))
        emitters = {"sky": {"type": "envmap", "bitmap": bitmap}}
    return emitters


def check_render_size(width, height, limits, source):
    """A :class:`GLTFError` where a ``width`` × ``height`` render has more pixels than ``limits``
    allow (``source``: where the size comes from)."""
    if width * height > limits.render_pixels:
        raise GLTFError(f"{source}: a {width}x{height} image has {width * height} pixels, more than a "
                        f"render may have ({limits.hint('render_pixels')})")
