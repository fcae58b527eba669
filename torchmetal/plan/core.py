"""The next K flash photos: an I-optimal design on the fit's information, plus highlight coverage.

**Criterion.** The quantity a user cares about is the error of renders under views not photographed. For the
least-squares fit, the part of that error a new photo can lower is the prediction variance of the renders,
so the plan minimises the *integrated prediction variance* (I-optimality, a.k.a. V-optimality) over a
reference set of views V — the same hand-held reachable set the candidates come from:

    E = Σ_v Σ_p Σ_c Var(Î_vpc) = Σ_pc G_aa/S_aa  +  Σ_e tr(H_e⁻¹ Q_e)

per pixel p and channel c, with the texture profiled out exactly as in :mod:`torchmetal.fit.uncertainty`:
S_xy = Σ_shots x·y/v (Fisher sums of the texture basis a, the lobe b and c = s·∂b/∂β, weighted by the
noise variance v(ŷ)), e_b = S_ab/S_aa, e_c = S_ac/S_aa, H_e = Σ_p the projected 2×2 normal matrix of
element e (channel × cluster), and G, Q the same sums over the reference views (Q: the views' projected
Jacobians). A candidate adds its own terms to every S; E is evaluated for all candidates at once.
Why I- rather than D-optimal: D (log det H) is invariant to how s and α are parametrised but blind to what
they are used for — it would spend photos pinning a parameter that changes no render; I weighs each
parameter by how much the renders move with it, texture included, so it ranks shots by the held-out error
they remove, which is the issue's target. (A-optimality, tr H⁻¹, would depend on the units of s vs log α.)

**Coverage.** E assumes the fitted structure (one s, α per cluster). A pixel where no photo ever put a
hotspot has only the structure's word for its specular — a second material there would go unseen. Each
pixel counts as seen where some shot's lobe reached half its peak there, the lobe taken at least as sharp as
:data:`HOT_ALPHA` (Phong α 100: the mirror direction within 6.7° of the view; a fitted lobe's own half-peak
region where it is sharper). A broad fitted lobe (α ≈ 7 on yellow_box) reaches half its peak over the whole
sample from any flash shot, so the map said every pixel's highlight was seen after one photo — true of that
lobe, and no word on where a sharper second material would show. The score adds
:data:`COVER_WEIGHT` × the fraction of the sample a candidate newly puts a hotspot on. Score =
(E − E')/E + COVER_WEIGHT·Δcover; weight 0.05: newly covering the whole sample is worth 5 % of E (a
typical shot newly covers 10–25 %: 0.5–1 % of E), so coverage breaks near-ties of E and does not override it.
(At 0.5 — a shot that halves E ranked with one covering the whole sample — the coverage term chose the
shot on most scenes, and on the bench's global-Phong scenes, where coverage cannot help, the planned shot
beat a random reachable one in 50 % of pairs; 82 % at 0.05, 86 % with E alone: docs/measurements.md,
2026-12-06.) When the fit saw **no highlight** (s = 0 everywhere), E has no specular to pin down and the
fitted α (its floor) says nothing of where a highlight would be: the hotspots are those of a typical gloss
(:data:`PROBE_ALPHA`) and coverage leads (:data:`UNSEEN_COVER_WEIGHT`).

**Reachable set** (a hand-held phone, flash beside the lens, docs/capture.md): the camera on shells around
the sample's centre at ``distance`` × the past shots' median distance, tilted ``tilts`` degrees from the
vertical, at ``azimuths`` directions, looking at the centre; the flash at the capture's offset from the lens
(the past shots' median light − camera, in the camera frame: OpenCV x right, y down, z forward) or at the
lens when the past lights are far from their cameras. Exposure: each shot's intensity scaled with its
squared light distance, as a phone's auto exposure keeps the image level.

K shots are chosen greedily (each one's terms added before the next is scored): best first, and the second
is the best *given* the first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchmetal.errors import InputError
from torchmetal.fit.grid_terms import block_terms
from torchmetal.fit.lobes import lobe_factor, lobe_terms
from torchmetal.geometry import pixel_axes

COVER_WEIGHT = 0.05
UNSEEN_COVER_WEIGHT = 1.0
PROBE_ALPHA = 100.0  # the gloss whose hotspots the coverage maps when the fit saw no highlight
HOT = 0.5  # a pixel is "in the highlight" of a shot where its lobe reaches this fraction of the lobe's peak
HOT_ALPHA = 100.0  # ... the lobe taken at least this sharp (module docstring: Coverage)
PRIOR = (1.0, 0.25, 1.0)  # prior precision of s, β and each texel (std 1, 2, 1): only matters with no past shots


@dataclass(frozen=True)
class PlanOptions:
    """shots: K; distance: camera distances as multiples of the past shots' median (or of ``default_distance``
    × the sample's width when none is known); tilts: degrees from the vertical; azimuths: directions per
    tilt; max_pixels: the planning grid's budget; views: reference views (a subset of the reachable set);
    cover_weight: the coverage term's weight (module docstring)."""

    shots: int = 3
    distance: tuple[float, ...] = (0.7, 1.0, 1.4)
    tilts: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0)
    azimuths: int = 16
    max_pixels: int = 1024
    views: int = 48
    default_distance: float = 5.0
    cover_weight: float = COVER_WEIGHT
    unseen_cover_weight: float = UNSEEN_COVER_WEIGHT

    def checked(self) -> PlanOptions:
        if self.shots < 1:
            raise InputError(f"plan: expected at least 1 shot to plan, found {self.shots}")
        if not self.distance or min(self.distance) <= 0 or not self.tilts or not all(0 <= t < 80 for t in self.tilts):
            raise InputError(f"plan: expected positive distances and tilts in [0, 80) degrees, found {self.distance}, {self.tilts}")
        if self.azimuths < 1 or self.max_pixels < 1 or self.views < 1:
            raise InputError(f"plan: expected azimuths, max_pixels, views >= 1, found {self.azimuths}, {self.max_pixels}, {self.views}")
        return self


@dataclass
class Scene:
    """What the plan knows: the fitted material on a grid and the past shots.

    texture (3, H, W); s, alpha (K, 3); labels (H, W) int64 or None; normals (3, H, W) or None (flat);
    size (width, height); lobe; lights, cameras (N, 4) and intensities (N, 3) of the past shots (N may be 0);
    noise: {"y": (3, B), "var": (3, B)} (:func:`torchmetal.fit.uncertainty.noise_variance`) or None;
    mask: (H, W) bool, the sample's pixels (None: all): only they count in E and in the coverage.
    """

    texture: Tensor
    s: Tensor
    alpha: Tensor
    labels: Tensor | None
    normals: Tensor | None
    size: tuple[float, float]
    lobe: str
    lights: Tensor
    cameras: Tensor
    intensities: Tensor
    noise: dict | None = None
    mask: Tensor | None = None


@dataclass
class Plan:
    """lights, cameras (K, 4) best first; scores (K,) each with the shots before it; error_drop (K,) the
    relative drop of E; cover_gain (K,); coverage (H', W') bool where a past shot put a hotspot (planning grid);
    planned_cover (K, H', W') bool where each planned shot does; flash offset (3,) in the camera frame;
    candidates: how many were scored; notes: what was assumed; intensities (K, 3): the exposure each planned
    shot was scored at (the past shots' level per squared light distance; not in plan.json); inside (H', W') bool:
    the sample's pixels on the planning grid (None: all)."""

    lights: Tensor
    cameras: Tensor
    scores: Tensor
    error_drop: Tensor
    cover_gain: Tensor
    coverage: Tensor
    planned_cover: Tensor
    offset: Tensor
    candidates: int
    notes: list
    intensities: Tensor | None = None
    inside: Tensor | None = None

    def seen(self) -> float:
        """The share of the sample's pixels where a past shot put the highlight."""
        cov = self.coverage if self.inside is None else self.coverage[self.inside]
        return float(cov.double().mean()) if cov.numel() else 0.0

    def to_json(self) -> dict:
        """DIR/plan.json's content, exactly docs/design.md §2.5's: {"shots": [{"light": [x, y, z, 1], "camera": […]}]}."""
        return {"shots": [{"light": [round(float(v), 6) for v in lt[:3]] + [1.0],
                           "camera": [round(float(v), 6) for v in cm[:3]] + [1.0]}
                          for lt, cm in zip(self.lights.tolist(), self.cameras.tolist())]}


# ------------------------------------------------------------------------------------- reachable set


def camera_frame(cam: Tensor, target: Tensor) -> Tensor:
    """(n, 3, 3) rows x, y, z of OpenCV camera frames at ``cam`` (n, 3) looking at ``target`` (3,): z forward,
    y down towards the sample's −y (its bottom edge appears at the image's bottom)."""
    z = torch.nn.functional.normalize(target - cam, dim=-1)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=cam.dtype).expand_as(z)
    y = -(up - (up * z).sum(-1, keepdim=True) * z)
    y = torch.nn.functional.normalize(y, dim=-1)
    x = torch.cross(y, z, dim=-1)
    return torch.stack([x, y, z], -2)


def flash_offset(lights: Tensor, cameras: Tensor) -> tuple[Tensor, str | None]:
    """The flash's offset from the lens in the camera frame (3,): the past shots' median; zero (and why) when
    they are not point lights beside point cameras."""
    zero = torch.zeros(3, dtype=torch.float64)
    if lights.shape[0] == 0:
        return zero, "no past shots: flash assumed at the lens"
    if not bool((lights[:, 3] == 1).all() and (cameras[:, 3] == 1).all()):
        return zero, "past lights or cameras are directions: flash assumed at the lens"
    cam, lt = cameras[:, :3].double(), lights[:, :3].double()
    rot = camera_frame(cam, torch.zeros(3, dtype=torch.float64))
    off = torch.einsum("nij,nj->ni", rot, lt - cam).median(0).values
    dist = float(cam.norm(dim=-1).median())
    if float(off.norm()) > 0.25 * dist:
        return zero, f"past lights are {float(off.norm()):.3g} from their cameras (not a flash): flash assumed at the lens"
    return off, None


def reachable(scene: Scene, o: PlanOptions) -> tuple[Tensor, Tensor, Tensor, list]:
    """Candidate (lights, cameras, intensities) (J, 4), (J, 4), (J, 3) and notes."""
    notes = []
    off, why = flash_offset(scene.lights, scene.cameras)
    if why:
        notes.append(why)
    points = scene.cameras[:, 3] == 1 if scene.cameras.shape[0] else torch.zeros(0, dtype=torch.bool)
    if bool(points.any()):
        base = float(scene.cameras[points, :3].double().norm(dim=-1).median())
    else:
        base = o.default_distance * float(max(scene.size))
        notes.append(f"no past camera position: distances relative to {base:.3g} ({o.default_distance} × the sample's width)")
    cams = []
    for r in o.distance:
        for tilt in o.tilts:
            n_az = 1 if tilt == 0 else o.azimuths
            for i in range(n_az):
                ph, th = 2 * math.pi * i / n_az, math.radians(tilt)
                cams.append([r * base * math.sin(th) * math.cos(ph), r * base * math.sin(th) * math.sin(ph), r * base * math.cos(th)])
    cam = torch.tensor(cams, dtype=torch.float64)
    rot = camera_frame(cam, torch.zeros(3, dtype=torch.float64))
    light = cam + torch.einsum("nji,j->ni", rot, off)  # camera frame → world: Rᵀ·offset
    light[:, 2] = light[:, 2].clamp_min(1e-3)
    ones = torch.ones(len(cams), 1, dtype=torch.float64)
    return torch.cat([light, ones], 1), torch.cat([cam, ones], 1), _intensity(scene, light), notes


def _intensity(scene: Scene, light: Tensor) -> Tensor:
    """(J, 3): the past shots' mean intensity per squared light distance (a phone's auto exposure keeps the image
    level), times each candidate's; without past point lights, the texture's mean at 0.25 in the centre."""
    d2 = (light[:, :3] ** 2).sum(-1, keepdim=True)
    pts = scene.lights[:, 3] == 1 if scene.lights.shape[0] else torch.zeros(0, dtype=torch.bool)
    if bool(pts.any()):
        per = (scene.intensities[pts].double() / (scene.lights[pts, :3].double() ** 2).sum(-1, keepdim=True)).mean(0)
        return d2 * per
    level = 0.25 / max(float(scene.texture.mean()), 1e-3)
    return d2 * level * torch.ones(1, 3, dtype=torch.float64)


# ------------------------------------------------------------------------------------- the criterion


def _grid(scene: Scene, max_pixels: int) -> tuple[int, slice, slice]:
    h, w = scene.texture.shape[-2:]
    stride = max(1, math.ceil(math.sqrt(h * w / max_pixels)))
    off = stride // 2
    return stride, slice(off, h, stride), slice(off, w, stride)


def shot_terms(scene: Scene, rows: slice, cols: slice, lights: Tensor, cams: Tensor, inten: Tensor) -> dict:
    """Per shot, channel, grid pixel (n, 3, P) float64: a, b, c = s·∂b/∂β, Fisher weight 1/v(ŷ), and the hotspot
    indicator (n, P) bool."""
    from torchmetal.fit.uncertainty import noise_variance

    h, w = scene.texture.shape[-2:]
    xs, ys = pixel_axes(h, w, scene.size, rows=rows, cols=cols, dtype=torch.float64)
    nrm = None if scene.normals is None else scene.normals[:, rows, cols].double()
    g, u, L, geo = block_terms(lights.double(), cams.double(), xs, ys, nrm, scene.lobe)
    n = int(lights.shape[0])
    p = int(xs.numel() * ys.numel())
    g, u, L = (t.reshape(n, 1, p) for t in (g, u, L))
    geo = None if geo is None else geo.reshape(3, n, p).transpose(0, 1)
    lab = None if scene.labels is None else scene.labels[rows, cols].reshape(-1)
    s_pix = scene.s[0].double().view(1, 3, 1) if lab is None else scene.s.double()[lab].T.unsqueeze(0)
    a_pix = scene.alpha[0].double().view(1, 3, 1) if lab is None else scene.alpha.double()[lab].T.unsqueeze(0)
    a, b, t = lobe_terms(g, u, L, inten.double().view(n, 3, 1), a_pix, geo, scene.lobe)
    inside = None if scene.mask is None else scene.mask[rows, cols].reshape(1, 1, p).to(torch.bool)
    if inside is not None:  # off the sample: no information, no render to predict, no highlight to see
        a, b = a * inside, b * inside
    tex = scene.texture[:, rows, cols].reshape(1, 3, p).double()
    pred = a * tex + s_pix * b
    v = (noise_variance(scene.noise, pred) if scene.noise is not None else 1e-4 * (pred.clamp_min(0) + 0.01)).clamp_min(1e-12)
    lit = u * inten.double().view(n, 3, 1)
    peak = (lit if inside is None else lit * inside).amax(-1, keepdim=True).clamp_min(1e-300)
    sharp = lit * lobe_factor(L, a_pix.clamp_min(HOT_ALPHA), geo, scene.lobe)
    hot = ((sharp / peak).amax(1) >= HOT) & (g[:, 0] > 0)
    if inside is not None:
        hot = hot & inside[:, 0]
    return {"a": a, "b": b, "c": s_pix * t * b, "w": 1.0 / v, "hot": hot, "labels": lab}


def fisher_sums(t: dict) -> Tensor:
    """(6, 3, P) Σ_shots w·(aa, ab, ac, bb, bc, cc)."""
    a, b, c, w = t["a"], t["b"], t["c"], t["w"]
    return torch.stack([(w * a * a).sum(0), (w * a * b).sum(0), (w * a * c).sum(0), (w * b * b).sum(0),
                        (w * b * c).sum(0), (w * c * c).sum(0)])


def view_sums(t: dict) -> Tensor:
    """(6, 3, P) Σ_views (aa, ab, ac, bb, bc, cc), unweighted: the reference views' render sensitivities."""
    return fisher_sums({**t, "w": torch.ones_like(t["w"])})


def expected_error(S: Tensor, G: Tensor, labels: Tensor | None, k: int) -> Tensor:
    """E (module docstring) for Fisher sums S (..., 6, 3, P) and view sums G (6, 3, P): (...)."""
    saa = S[..., 0, :, :] + PRIOR[2]
    eb, ec = S[..., 1, :, :] / saa, S[..., 2, :, :] / saa
    h = torch.stack([S[..., 3, :, :] - eb * S[..., 1, :, :], S[..., 4, :, :] - eb * S[..., 2, :, :],
                     S[..., 5, :, :] - ec * S[..., 2, :, :]], -1)
    gaa, gab, gac, gbb, gbc, gcc = G.unbind(0)
    q = torch.stack([gbb - 2 * eb * gab + eb * eb * gaa, gbc - eb * gac - ec * gab + eb * ec * gaa,
                     gcc - 2 * ec * gac + ec * ec * gaa], -1)
    if labels is None or k == 1:
        H, Q = h.sum(-2), q.sum(-2)  # (..., 3 channels, 3 components)
    else:  # per cluster: (..., K, 3, 3)
        shape = (*h.shape[:-3], k, 3, 3)
        H = torch.zeros(shape, dtype=h.dtype).index_add_(len(shape) - 3, labels, h.movedim(-2, -3))
        Q = torch.zeros(shape, dtype=q.dtype).index_add_(len(shape) - 3, labels, q.movedim(-2, -3))
    h11, h12, h22 = H[..., 0] + PRIOR[0], H[..., 1], H[..., 2] + PRIOR[1]
    det = (h11 * h22 - h12 * h12).clamp_min(1e-300)
    glob = (h22 * Q[..., 0] - 2 * h12 * Q[..., 1] + h11 * Q[..., 2]) / det
    batch = len(S.shape) - 3
    return (gaa / saa).flatten(batch).sum(-1) + glob.flatten(batch).sum(-1)


def _context(scene: Scene, o: PlanOptions, reference: tuple | None = None) -> dict:
    """What every score needs: the (probed, when no highlight was seen) scene, the reachable candidates and their
    terms, the reference views' sums G (of ``reference`` = (lights, cameras, intensities) when given, else of
    ``o.views`` reachable ones), the past shots' Fisher sums S and hotspot coverage."""
    unseen = not bool((scene.s > 0).any())
    if unseen:  # no highlight seen (s = 0, α at its floor): hotspots where a highlight of a typical gloss would be
        scene = replace(scene, alpha=torch.full_like(scene.alpha, PROBE_ALPHA))
    lights, cams, inten, notes = reachable(scene, o)
    stride, rows, cols = _grid(scene, o.max_pixels)
    cand = shot_terms(scene, rows, cols, lights, cams, inten)
    if reference is None:
        pick = torch.linspace(0, lights.shape[0] - 1, min(o.views, lights.shape[0])).round().long()
        G = view_sums({key: (v[pick] if key not in ("labels",) else v) for key, v in cand.items()})
    else:
        G = view_sums(shot_terms(scene, rows, cols, *(t.double() for t in reference)))
    p = int(cand["a"].shape[-1])
    if scene.lights.shape[0]:
        past = shot_terms(scene, rows, cols, scene.lights, scene.cameras, scene.intensities)
        S, covered = fisher_sums(past), past["hot"].any(0)
    else:
        S, covered = torch.zeros(6, 3, p, dtype=torch.float64), torch.zeros(p, dtype=torch.bool)
    # no highlight seen: E knows no specular to pin down (s = 0), and finding the highlight comes first
    return {"scene": scene, "lights": lights, "cams": cams, "inten": inten, "notes": notes, "rows": rows, "cols": cols,
            "cand": cand, "G": G, "S": S, "covered": covered, "k": int(scene.s.shape[0]),
            "cover_weight": o.unseen_cover_weight if unseen else o.cover_weight,
            "inside": torch.ones(p, dtype=torch.bool) if scene.mask is None else scene.mask[rows, cols].reshape(-1).bool()}


def _per_shot(t: dict) -> Tensor:
    """(n, 6, 3, P) each shot's own Fisher terms (:func:`fisher_sums` before the sum over shots)."""
    a, b, c, w = t["a"], t["b"], t["c"], t["w"]
    return torch.stack([w * a * a, w * a * b, w * a * c, w * b * b, w * b * c, w * c * c], 1)


def score_shots(scene: Scene, lights: Tensor, cameras: Tensor, intensities: Tensor,
                options: PlanOptions | None = None, reference: tuple | None = None) -> dict:
    """The plan's score of given shots (n, 4), (n, 4), (n, 3) — e.g. a capture's own, held back — each as the
    one next shot after the scene's past ones: {"score", "error_drop", "cover_gain"} (n,) float64. The same
    criterion as :func:`plan_shots`' first pick; reference views: the reachable set's, or ``reference`` =
    (lights, cameras, intensities) when given."""
    o = (options or PlanOptions()).checked()
    ctx = _context(scene, o, reference)
    t = shot_terms(ctx["scene"], ctx["rows"], ctx["cols"], lights, cameras, intensities)
    e0 = expected_error(ctx["S"], ctx["G"], t["labels"], ctx["k"])
    e1 = expected_error(ctx["S"].unsqueeze(0) + _per_shot(t), ctx["G"], t["labels"], ctx["k"])
    drop = (e0 - e1) / e0.clamp_min(1e-300)
    gain = (t["hot"] & ~ctx["covered"]).double().sum(-1) / max(int(ctx["inside"].sum()), 1)
    return {"score": drop + ctx["cover_weight"] * gain, "error_drop": drop, "cover_gain": gain}


def plan_shots(scene: Scene, options: PlanOptions | None = None) -> Plan:
    """The next ``options.shots`` positions (module docstring), best first."""
    o = (options or PlanOptions()).checked()
    ctx = _context(scene, o)
    lights, cams, inten, cand, lab, k = ctx["lights"], ctx["cams"], ctx["inten"], ctx["cand"], ctx["cand"]["labels"], ctx["k"]
    G, S, covered, cover_weight = ctx["G"], ctx["S"], ctx["covered"], ctx["cover_weight"]
    h, w = scene.texture.shape[-2:]
    hr, wr = len(range(*ctx["rows"].indices(h))), len(range(*ctx["cols"].indices(w)))
    per = _per_shot(cand)
    n_inside = max(int(ctx["inside"].sum()), 1)
    free = torch.ones(lights.shape[0], dtype=torch.bool)
    chosen, scores, drops, gains, planned = [], [], [], [], []
    past_cover = covered.clone()
    for _ in range(min(o.shots, lights.shape[0])):
        e0 = expected_error(S, G, lab, k)
        e1 = expected_error(S.unsqueeze(0) + per, G, lab, k)
        drop = (e0 - e1) / e0.clamp_min(1e-300)
        gain = (cand["hot"] & ~covered).double().sum(-1) / n_inside
        score = torch.where(free, drop + cover_weight * gain, torch.full_like(drop, -math.inf))
        j = int(score.argmax())
        chosen.append(j)
        scores.append(float(score[j]))
        drops.append(float(drop[j]))
        gains.append(float(gain[j]))
        planned.append(cand["hot"][j].view(hr, wr))
        S = S + per[j]
        covered = covered | cand["hot"][j]
        free[j] = False
    idx = torch.tensor(chosen, dtype=torch.long)
    return Plan(lights=lights[idx], cameras=cams[idx], scores=torch.tensor(scores), error_drop=torch.tensor(drops),
                cover_gain=torch.tensor(gains), coverage=past_cover.view(hr, wr), planned_cover=torch.stack(planned),
                offset=flash_offset(scene.lights, scene.cameras)[0], candidates=int(lights.shape[0]), notes=ctx["notes"],
                intensities=inten[idx], inside=None if scene.mask is None else ctx["inside"].view(hr, wr))
