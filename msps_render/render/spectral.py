"""Spectral rendering: SceneSpec (mode "spectral") -> Frame with camera-channel images.

Called by `render_frame` (which sets a spectral variant).
Reuses the RGB scene description and edits it:

* the film becomes a `specfilm` whose three bands are the camera's r, g, b
  sensitivities (so a pixel is Σ_λ L(λ) S_i(λ) Δλ, verified against colour-science
  to <2% in tests/test_spectral.py);
* light k emits its spectrum (`LightSpec.spectrum`), scaled so that its camera
  response on a white reflector at normal incidence, summed over channels,
  equals `sum(LightSpec.rgb)`; a light without a spectrum keeps Mitsuba's own
  RGB->spectrum upsampling of `rgb`.  By default each light is rendered alone
  with its emission folded into the film bands (E_k·S_i, unit flat emission),
  which importance-samples wavelengths by emission x camera instead of camera
  only (see `_render_light_in_film`): identical expectation, ~10-30x less colour
  noise for narrow LEDs;
* RGB materials (and the MERL plugin) are upsampled to spectra by Mitsuba;
* the environment's radiance is corrected (`build_scene_dict(env_factor=...)`)
  so its camera response summed over channels equals its RGB-mode channel sum
  (see `env_spectral_factor`), so `EnvSpec.ratio` means the same in both modes.

The effective crosstalk (columns: share of each light's signal per channel) is
computed from the spectra and stored in `frame.spec.crosstalk` and `frame.meta`.

Spectral rigs (`SceneSpec.rig` with `RigSpec.crosstalk`, msps_render.rig): the camera has M
channels (narrow-band filters or a measured table), so the bands above are the rig's M
sensitivities (`rig_sensitivities`), every per-light and environment image has M channels,
and the frame's `shots` (S, H, W, M) are sums of them (`compose_shots`).  `image` is then a
display image only: the sum of all lights, each channel shown in the colour of its band
(`spectra.display_weights`).
"""
from __future__ import annotations

import numpy as np

from msps_render.errors import InputError
from msps_render.frame import Frame
from msps_render.render.emitters import render_emitters_one_pass, render_emitters_separately
from msps_render.render.ground_truth import ground_truth, pixel_points
from msps_render.render.multilight import integrator_dict
from msps_render.render.scene_dict import ENV_KEY, build_scene_dict, light_key, one_pass, with_lights
from msps_render.rig import compose_shots, rig_sensitivities
from msps_render.scene.envmap import envmap_pixels, irradiance_on_axis
from msps_render.scene.spec import SceneSpec
from msps_render.spectral.spectra import GRID, WL_STEP, camera_sensitivities, display_weights, light_spectrum

DEFAULT_CAMERA = "Nikon 5100 (NPL)"


def _irregular(values: np.ndarray) -> dict:
    return {"type": "irregular", "wavelengths": ", ".join(f"{w:g}" for w in GRID),
            "values": ", ".join(f"{float(v):.9g}" for v in values)}


def specfilm(spec: SceneSpec, S: np.ndarray) -> dict:
    """A `specfilm` whose bands are the columns of S (on GRID), e.g. camera r, g, b (or M channels)."""
    film = {"type": "specfilm", "width": spec.camera.width, "height": spec.camera.height,
            "rfilter": {"type": "box"}, "component_format": "float32"}
    m = S.shape[1]
    names = ("red", "green", "blue") if m == 3 else tuple(f"c{i}" for i in range(m))
    for i, name in enumerate(names):
        film[f"band{i:0{len(str(m - 1))}d}_{name}"] = _irregular(S[:, i])  # bands are ordered by key
    return film


def emitter_spectrum_for_rgb(mi, rgb) -> np.ndarray:
    """Mitsuba's emission spectrum (on GRID) for an RGB emitter value in the active spectral variant."""
    import drjit as dr

    em = mi.load_dict({"type": "constant", "radiance": {"type": "rgb", "value": [float(c) for c in rgb]}})
    n = len(GRID)
    if dr.is_jit_v(mi.Float):
        m = -(-n // 4)
        w = np.concatenate([GRID, np.full(4 * m - n, GRID[-1])]).reshape(4, m, order="F")
        si = dr.zeros(mi.SurfaceInteraction3f, m)
        si.wavelengths = type(si.wavelengths)(*[mi.Float(w[j]) for j in range(4)])
        si.wi = mi.Vector3f(0, 0, 1)
        v = em.eval(si)
        return np.stack([np.array(v[j]) for j in range(4)], 0).reshape(-1, order="F")[:n].astype(np.float64)
    out = np.zeros(n)
    for a in range(0, n, 4):
        w = [float(GRID[min(a + j, n - 1)]) for j in range(4)]
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wavelengths = type(si.wavelengths)(*w)
        si.wi = mi.Vector3f(0, 0, 1)
        v = em.eval(si)
        for j in range(4):
            if a + j < n:
                out[a + j] = float(v[j])
    return out


def _sensitivities(camera) -> np.ndarray:
    """(len(GRID), M): a camera id's r, g, b sensitivities, or an array of them as given."""
    return camera_sensitivities(camera).values if isinstance(camera, str) else np.asarray(camera)


def env_spectral_factor(mi, spec: SceneSpec, camera_id) -> float:
    """Factor on `EnvSpec.scale` so the env's channel-summed camera response matches RGB mode.

    Uses the env's mean colour on a camera-facing plane (exact for a uniformly
    coloured map; for real maps the error is the nonlinearity of RGB->spectrum
    upsampling across the map's colours, small for sky-like maps).
    """
    e = spec.environment
    E = irradiance_on_axis(envmap_pixels(e.source, e.seed), (0.0, 0.0, 1.0), e.rotation_deg)
    if E.max() <= 0:
        return 1.0
    c = E / E.max()
    resp = emitter_spectrum_for_rgb(mi, c) @ _sensitivities(camera_id) * WL_STEP
    return float(c.sum() / max(resp.sum(), 1e-12))


def light_shape(mi, light, S: np.ndarray) -> tuple[np.ndarray, float]:
    """(shape, scale) of a light's emission spectrum on GRID, E = shape * scale: a spectrum id's own shape,
    scaled so its camera response summed over channels is `sum(rgb)`; Mitsuba's upsampling of `rgb` (scale 1)
    otherwise.  Frames in batches share the shape (its wavelength table) and keep their own scale."""
    if light.spectrum is not None:
        unit = light_spectrum(light.spectrum).values
        r_unit = unit @ S * WL_STEP
        return unit, sum(light.rgb) / max(r_unit.sum(), 1e-300)
    return emitter_spectrum_for_rgb(mi, light.rgb), 1.0


def light_responses(mi, spec: SceneSpec, camera_id) -> tuple[list[np.ndarray], np.ndarray]:
    """Per light: its emission spectrum on GRID (absolute) and its (M,) camera response (white, normal);
    `camera_id`: a camera id (M = 3) or the sensitivities themselves, (len(GRID), M)."""
    S = _sensitivities(camera_id)
    spectra, R = [], []
    for l in spec.lights:
        shape, scale = light_shape(mi, l, S)
        E = shape * scale
        spectra.append(E)
        R.append(E @ S * WL_STEP)
    return spectra, (np.stack(R, axis=1) if R else np.zeros((S.shape[1], 0)))


def camera_bands(spec: SceneSpec) -> tuple[object, np.ndarray]:
    """(camera id, (len(GRID), M) sensitivities) of a spectral frame: its rig's M channels, or its camera's
    r, g, b.  A rig of weights on R, G, B is refused: it belongs to mode 'rgb'."""
    rig = spec.rig
    if rig is not None and not rig.is_spectral:
        raise InputError("scene.rig", "this rig's channels are weights on R, G, B (mode 'rgb'); a spectral scene's "
                                      "rig needs spectral channels (sample it with scene.mode = 'spectral')")
    if rig is not None:
        return rig.camera, rig_sensitivities(rig)
    camera_id = spec.camera_response or DEFAULT_CAMERA
    return camera_id, camera_sensitivities(camera_id).values


def _render(mi, scene, spec: SceneSpec, channels: int = 3) -> np.ndarray:
    return np.array(mi.render(scene, spp=spec.integrator.spp, seed=spec.integrator.seed),
                    dtype=np.float32)[..., :channels]


def _render_light_in_film(mi, spec: SceneSpec, k: int, E: np.ndarray, S: np.ndarray):
    """Light k alone, with its emission folded into the film: unit flat emission, bands E_k·S_i.

    Why: `specfilm` draws wavelengths from Σ_i band_i.  With bands S_i and a narrow
    LED most wavelength samples miss the LED (measured 11% per-pixel noise in red at
    128 spp for led:630:20); with bands E_k·S_i the draw follows the product, so the
    only wavelength noise left comes from the reflectance spectrum (a few tenths of
    a percent).  Transport is linear in the emission at each wavelength, so
    ∫ (E_k T) S_i dλ = ∫ T (E_k S_i) dλ: same expectation, same image.
    A band with no mass (a narrow LED far from a narrow filter: Mitsuba refuses it) is left out of
    the film and its channel is 0.
    """
    l = spec.lights[k]
    sub = spec.model_copy(update={"lights": (l,), "environment": None})
    d = build_scene_dict(sub, mi)
    B = S * E[:, None]
    peak = B.max(axis=0)
    live = np.flatnonzero(peak > 1e-20 * peak.max())
    d["sensor"]["film"] = specfilm(spec, B if len(live) == B.shape[1] else B[:, live])
    d[light_key(0)]["irradiance" if l.kind == "directional" else "intensity"] = {"type": "uniform", "value": 1.0}
    scene = mi.load_dict(d)
    img = _render(mi, scene, spec, len(live))
    if len(live) == B.shape[1]:
        return scene, img
    out = np.zeros(img.shape[:2] + (B.shape[1],), np.float32)
    out[..., live] = img
    return scene, out


def one_pass_dict(mi, spec: SceneSpec, S: np.ndarray, spectra: list[np.ndarray], R: np.ndarray,
                  env_factor: float | None, slots=None) -> tuple[dict, list[str], dict]:
    """(scene dict, emitter ids, bands per emitter id) of a one-pass spectral render: lights emit a flat
    unit spectrum, their emission folded into their bands; load the dict, then give the integrator the
    bands (`set_bands(GRID, bands)`).  Only the lights the camera sees are traced."""
    visible = [k for k in range(len(spec.lights)) if R[:, k].sum() > 0]  # the camera sees light k
    ids = [light_key(k) for k in visible] + ([ENV_KEY] if spec.environment is not None else [])
    integ = spec.integrator
    d = build_scene_dict(spec, mi, env_factor=env_factor or 1.0, slots=slots)  # env scale x factor in its bitmap
    mus = list(spec.rig.anisotropy) if spec.rig is not None and spec.rig.anisotropy else []
    d["integrator"] = integrator_dict(integ.kind, integ.max_depth, ids, hide_emitters=True,
                                      anisotropy=[mus[k] for k in visible] + [0.0] * (len(ids) - len(visible))
                                      if mus else (), channels=S.shape[1])
    for k, l in enumerate(spec.lights):
        d[light_key(k)]["irradiance" if l.kind == "directional" else "intensity"] = {"type": "uniform", "value": 1.0}
    bands = {light_key(k): S * spectra[k][:, None] for k in visible}
    if spec.environment is not None:
        bands[ENV_KEY] = S
    return d, ids, bands


def _render_one_pass(mi, spec: SceneSpec, S: np.ndarray, spectra: list[np.ndarray], R: np.ndarray,
                     env_factor: float | None, slots=None):
    """Every emitter from ONE render (`msps_multilight`), with the emission folded into each
    emitter's own bands as `_render_light_in_film` does: light k emits a flat unit spectrum and its
    four wavelengths per path are drawn from its bands E_k·S_i, the environment's from S_i.
    Returns (ground truth, images: lights in order, then the environment)."""
    integ = spec.integrator
    d, ids, bands = one_pass_dict(mi, spec, S, spectra, R, env_factor, slots)
    scene = mi.load_dict(d)
    gt = ground_truth(mi, scene, spec)
    zero = np.zeros(gt[0].shape[:2] + (S.shape[1],), np.float32)
    if not ids:  # no visible light and no environment: geometry only
        return gt, [zero.copy() for _ in spec.lights]
    scene.integrator().set_bands(GRID, bands)
    got = dict(zip(ids, render_emitters_one_pass(mi, scene, ids, integ.spp, integ.seed)))
    images = [got.get(light_key(k), zero) for k in range(len(spec.lights))]
    if spec.environment is not None:
        images.append(got[ENV_KEY])
    return gt, images


def render_spectral_frame(spec: SceneSpec, mi, variant: str, per_light: bool = False,
                          emission_in_film: bool = True, slots=None) -> Frame:
    """Render a spectral SceneSpec. `emission_in_film=False` renders the literal set-up (lights
    emit their spectra, film bands = camera sensitivities; always one render per emitter): same
    expectation, much noisier for narrow LEDs; kept for validation (tests compare both).
    A spectral rig (`spec.rig.is_spectral`) renders its M channels and composes its shots.
    `slots`: the worker's BSDF slots for the one-pass render (`render.slots`; the same pixels)."""
    camera_id, S = camera_bands(spec)
    if spec.rig is not None and not emission_in_film and S.shape[1] != 3:
        raise ValueError(f"the literal spectral set-up reads three channels; this rig has {S.shape[1]} "
                         f"(render it with emission_in_film=True)")
    spectra, R = light_responses(mi, spec, S)
    env_factor = env_spectral_factor(mi, spec, S) if spec.environment is not None else None
    gt = None
    lights_mode = "one-pass" if emission_in_film and one_pass(spec, mi) else "per-light"
    if lights_mode == "one-pass":
        gt, images = _render_one_pass(mi, spec, S, spectra, R, env_factor, slots)
    elif emission_in_film:
        ref = with_lights(spec, "per-light")  # the reference: one Mitsuba render per emitter
        images = []
        for k in range(len(spec.lights)):
            if R[:, k].sum() <= 0:  # the camera does not see this light at all
                images.append(None)
                continue
            scene, img = _render_light_in_film(mi, ref, k, spectra[k], S)
            gt = gt or ground_truth(mi, scene, spec)
            images.append(img)
        if spec.environment is not None:
            d = build_scene_dict(ref.model_copy(update={"lights": ()}), mi, env_factor=env_factor)
            d["sensor"]["film"] = specfilm(spec, S)
            scene = mi.load_dict(d)
            gt = gt or ground_truth(mi, scene, spec)
            images.append(_render(mi, scene, spec, S.shape[1]))
        if gt is None:  # no visible light: geometry only
            scene = mi.load_dict(build_scene_dict(ref, mi))
            gt = ground_truth(mi, scene, spec)
        zero = np.zeros(gt[0].shape[:2] + (S.shape[1],), np.float32)
        images = [zero if im is None else im for im in images]
    else:
        ref = with_lights(spec, "per-light")
        d = build_scene_dict(ref, mi, env_factor=env_factor or 1.0)
        d["sensor"]["film"] = specfilm(spec, S)
        for k, (l, E) in enumerate(zip(spec.lights, spectra)):
            d[light_key(k)]["irradiance" if l.kind == "directional" else "intensity"] = _irregular(E)
        scene = mi.load_dict(d)
        gt = ground_truth(mi, scene, spec)
        images = render_emitters_separately(mi, scene, ref)
    return spectral_frame(mi, spec, variant, gt, images, S, R, camera_id, env_factor, per_light,
                          "emission x camera" if emission_in_film else "camera", lights_mode)


def spectral_frame(mi, spec: SceneSpec, variant: str, gt: tuple, images: list, S: np.ndarray, R: np.ndarray,
                   camera_id, env_factor: float | None, per_light: bool, sampling: str, lights_mode: str) -> Frame:
    """The Frame of a spectral render: per-emitter M-channel images (lights, then the environment) summed,
    the rig's shots composed, the effective crosstalk and the light responses `R` in its meta.  Shared by
    one frame at a time and frames in batches (`render.batch`)."""
    rig = spec.rig
    normal, mask, depth, part = gt
    images = list(images)
    env_img = images.pop() if spec.environment is not None else None
    per = np.stack(images) if images else np.zeros((0,) + normal.shape[:2] + (S.shape[1],), np.float32)
    image = per.sum(axis=0) + (env_img if env_img is not None else 0.0)

    s = R.sum(axis=0)
    M = R / np.where(s > 0, s, 1.0)
    shots = points = None
    if rig is not None:  # the rig's camera images; `image` shows their channels in colour
        shots = compose_shots(rig, per, env_img)
        if any(l.kind == "point" for l in spec.lights):
            points = pixel_points(spec.camera, depth, mask)
        if rig.filters or S.shape[1] != 3:
            image = image @ display_weights(S).astype(np.float32)
        out_spec = spec  # C is the rig's (RigSpec.crosstalk x the lights' sums), not a 3 x 3 SceneSpec.crosstalk
    else:
        update = {"camera_response": camera_id}
        if len(spec.lights) == 3:
            update["crosstalk"] = tuple(tuple(float(x) for x in row) for row in M)
        out_spec = spec.model_copy(update=update)
    meta = {"mitsuba_version": mi.__version__, "camera_response": camera_id,
            "crosstalk_effective": M.tolist(), "light_response": R.tolist(),
            "light_spectra": [l.spectrum for l in spec.lights], "env_spectral_factor": env_factor,
            "wavelength_sampling": sampling, "lights": lights_mode,
            "wavelength_range_nm": [float(GRID[0]), float(GRID[-1])]}
    if rig is not None:
        meta.update(channel_names=list(rig.channel_names), filters_nm=[list(f) for f in rig.filters],
                    image="display: channels shown in the colour of their bands" if rig.filters or S.shape[1] != 3
                    else "sum of the shots' channels")
    return Frame(image=np.ascontiguousarray(image[..., :3], dtype=np.float32), normal=normal, mask=mask,
                 depth=depth, part=part, spec=out_spec, variant=variant,
                 per_light=per if per_light else None, env_image=env_img, meta=meta, shots=shots, points=points)
