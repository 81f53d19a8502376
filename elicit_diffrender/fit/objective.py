"""The ELICIT objective: each step's unweighted loss terms by name, weighted in one place (``total``).

* stage 1: a patch of a body-prior render from a ring camera: ``perceptual``, ``mse``, ``alpha``;
* stage 2, input step: a patch of the input photo: ``perceptual``, ``mse``;
* stage 2, novel step: a hybrid-sampled (pose, camera, part) crop: ``silhouette`` and ``edge`` against
  the body's mask, ``opacity`` (binary entropy), ``semantic`` against a reference crop (with a CLIP or
  random-features encoder), ``text``;
* every step: ``tv`` (grid smoothness) and, in stage 2, ``sparsity`` (density outside the body) and,
  when the semantic prior falls back to the weights-free mirror completion, ``mirror``.

A term whose weight is 0 is not computed.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
import torch
from scipy.spatial import cKDTree

from ..body import PART_NAMES, BodyModel
from ..body.template import vertex_normals
from ..core.host_reads import on_host
from ..model.encoders import FALLBACK_NAME, EncoderError, load_encoder
from ..model.field import CanonicalField, grid_axes, nearest, node_points
from ..model.losses import Perceptual, edge_distance, edge_loss, mse, opacity_entropy, semantic_loss, silhouette_loss
from ..model.total_variation import total_variation
from .completion import MirrorCompletion, behind_body, exit_depth
from .config import FitConfig
from .hybrid_sampling import NovelView, crop_window, part_pixels, plan_novel_view
from .regions import GradRegions
from .render import PoseRenderer
from .room import canonical_to_pose
from .streams import RandomStreams
from .views import FitViews, InputView, crop_image, min_part_pixels, random_patch

# Loss term -> the config key of its weight.
TERMS = {
    "perceptual": "w_perceptual",
    "mse": "w_mse",
    "alpha": "w_init_alpha",
    "silhouette": "w_silhouette",
    "edge": "w_edge",
    "opacity": "w_opacity",
    "semantic": "w_semantic",
    "mirror": "w_mirror",
    "text": "w_text",
    "tv": "w_tv",
    "sparsity": "w_sparsity",
}
Terms = dict[str, torch.Tensor]
PHOTO_REFERENCE_DEG = 45.0  # a novel view's semantic reference is an input photo this close to it in yaw
log = logging.getLogger("elicit.fit")


def outside_body(
    body_sdf: np.ndarray, field: CanonicalField, device: torch.device, hull: np.ndarray | None
) -> torch.Tensor:
    """1 for grid cells more than one cell outside the canonical body (``body_sdf``: ``field.body_distance``;
    where density is clothing), except the ``hull`` cells (flat bool: the room's hulls of the hair and of a
    garment that bridges the legs, whose depth is a prior's)."""
    outside = body_sdf.reshape(-1) > field.voxel_size
    if hull is not None:
        outside &= ~hull
    return torch.as_tensor(outside.reshape(field.shape), dtype=torch.float32, device=device)


def source_photos(seen: np.ndarray, held: np.ndarray, facing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which photo each body vertex takes its colour from, given every photo's (photos, V) ``seen``, ``held``
    (seen, but maybe behind what the hands hold) and ``facing`` (cosine to the camera): the one that sees it most
    squarely clear of the hands, else the one that sees it most squarely. Returns the (V,) photo indices and the
    (V,) vertices that no photo shows clear of the hands (seen, but only as held)."""
    clear = np.where(seen & ~held, facing, -np.inf)
    any_clear = np.isfinite(clear.max(0))
    best = np.where(any_clear, clear.argmax(0), np.where(seen, facing, -np.inf).argmax(0))
    return best, seen.any(0) & ~any_clear


class Objective:
    def __init__(
        self,
        cfg: FitConfig,
        views: FitViews,
        renderer: PoseRenderer,
        streams: RandomStreams,
        body: BodyModel,
        body_sdf: np.ndarray,
        hull: np.ndarray | None = None,
    ) -> None:
        """``body_sdf``: the canonical body's signed distance at the grid's nodes (``field.body_distance``);
        ``hull``: flat bool over the grid's cells, the room's hulls (hair, a garment between the legs: :mod:`.room`)."""
        self.cfg, self.views, self.renderer, self.streams = cfg, views, renderer, streams
        self.device = renderer.avatar.device
        self.field = renderer.avatar.field
        self.weights = {name: float(getattr(cfg, key)) for name, key in TERMS.items()}
        self.encoder, self.encoder_info, self.completion = None, None, None
        # The completed cells on the body's far side in every observed photo. A photo's patch could still reach
        # them through a soft or thin front (a held folder's colour on the back's waist, a white side stripe on the
        # backs of the legs, the collar on the nape), so photo steps leave their colour to the completion.
        self.behind: torch.Tensor | None = None
        if self.on("semantic") or self.on("text"):
            self.encoder, self.encoder_info = load_encoder(cfg.encoder, cfg.clip_model, cfg.clip_pretrained)
            if self.encoder is not None:
                self.encoder.to(self.device)
        if self.encoder_info is not None and self.encoder_info.kind == "mirror":
            if cfg.text_prompt and self.on("text"):
                raise EncoderError(f"text_prompt needs CLIP weights; the semantic prior here is {FALLBACK_NAME}")
            if self.on("semantic") and self.on("mirror"):
                self.completion = self._mirror_completion(body, body_sdf, cfg.box_margin, hull)
                self.behind = self._behind_every_photo(body, self.completion.cells)
                log.info(
                    "%d of the %d completed cells lie on the body's far side in every photo: photo patches leave "
                    "their colour alone",
                    self.behind.numel(),
                    len(self.completion),
                )
        self.text_embedding = None
        if cfg.text_prompt and self.on("text") and self.encoder is not None:
            self.text_embedding = self.encoder.encode_text(cfg.text_prompt)
        self.perceptual = Perceptual(cfg.perceptual, self.device)
        self.far_side = self._far_side_layer(body, body_sdf, cfg.far_side_layer)
        if self.far_side.any():
            log.info(
                "far side: %d cells within %.3f m of the body, behind it in the first photo, are clothing",
                int(self.far_side.sum()),
                cfg.far_side_layer,
            )
        exempt = self.far_side if hull is None else hull | self.far_side
        self.outside_body = outside_body(body_sdf, self.field, self.device, exempt) if self.on("sparsity") else None
        self.skipped_references = 0  # semantic steps without a usable reference crop
        self.regions = GradRegions()  # the grid regions the step's regularisers read
        self.photo_step = False  # this step reconstructs a patch of an input photo

    def _mirror_completion(
        self, body: BodyModel, body_sdf: np.ndarray, margin: float, hull: np.ndarray | None
    ) -> MirrorCompletion:
        """The completion of the cells no observed photo sees; each vertex takes its colour and facing from the
        photo that sees it most squarely clear of the hands (of those that see it, if none does), the light is the
        first photo's."""
        view = self.views.input
        canon = body.pose(body.canonical_pose())
        normals = vertex_normals(canon.vertices, body.faces)
        light = view.shading(view.normals)
        observed = self.views.observed
        seen_by, facing_by = np.stack([v.seen for v in observed]), np.stack([v.facing for v in observed])  # (photos, V)
        best, held = source_photos(seen_by, np.stack([v.held for v in observed]), facing_by)
        seen = seen_by.any(0)
        colors = np.stack([v.colors for v in observed])[best, np.arange(best.size)]
        facing = np.where(seen, facing_by[best, np.arange(best.size)], view.facing)
        pairs = MirrorCompletion.build(
            self.field,
            canon.vertices,
            normals,
            body.vertex_parts(),
            seen,
            body_sdf,
            margin,
            light,
            hull,
            colors,
            facing,
            self.cfg.completion,
            held,
        )
        rules = ", ".join(f"{name} {n}" for name, n in pairs.rule_counts.items())
        log.info(
            "semantic prior: %s; %.0f%% of the body's vertices seen (%.0f%% of them within the reach of forearms "
            "held in front: no source); %d of %d unseen colour cells have a source (%s); the photo's light: "
            "key/ambient %.2f from %s",
            FALLBACK_NAME,
            100 * seen.mean(),
            100 * held.sum() / max(seen.sum(), 1),
            len(pairs),
            pairs.unseen,
            rules,
            view.shading.ratio,
            np.round(view.shading.direction, 2).tolist(),
        )
        return pairs

    def _behind_every_photo(self, body: BodyModel, cells: torch.Tensor) -> torch.Tensor:
        """Those of the colour grid's ``cells`` (flat indices) whose place in every observed photo's pose lies on the
        body's far side in that photo (:func:`behind_body`)."""
        index = cells.cpu().numpy()
        behind = self._behind(body, self._node_points(index))
        return torch.as_tensor(index[behind], dtype=torch.long, device=self.device)

    def _node_points(self, index: np.ndarray) -> np.ndarray:
        """(N, 3) the canonical positions of the grid's nodes ``index`` (flat)."""
        axes = [a.numpy() for a in grid_axes(self.field.box.double(), self.field.shape)]
        return node_points(axes, np.unravel_index(index, self.field.shape))

    def _behind(self, body: BodyModel, points: np.ndarray) -> np.ndarray:
        """(N,) bool: canonical ``points`` whose place in every observed photo's pose lies on the body's far side in
        that photo (:func:`behind_body`)."""
        behind = np.ones(len(points), dtype=bool)
        for view in self.views.observed:
            behind &= self._far_side_in(view, body, points)[0]
        return behind

    @staticmethod
    def _far_side_in(view: InputView, body: BodyModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) bool: canonical ``points`` on the body's far side in ``view`` (:func:`behind_body`), and their (N, 3)
        places in its pose."""
        posed = canonical_to_pose(body, view.posed)(points)
        far = exit_depth(view.posed.vertices, view.camera, view.depth)
        return behind_body(posed, view.camera, view.depth, far), posed

    def _far_side_layer(self, body: BodyModel, body_sdf: np.ndarray, thickness: float) -> np.ndarray:
        """Flat bool over the grid's cells: those within ``thickness`` outside the canonical body, off the head,
        that the first photo cannot see and the others allow (:meth:`_hidden_from_the_first_photo`). The body is
        fitted to the photo's outline, not to the clothes' depth, so the clothing a photo shows in front of the body
        has no counterpart behind it, and side and rear views come out thinner than the person; these cells are that
        counterpart (stage 2 starts with them opaque). The head's back is the hair hull's (:mod:`.room`)."""
        layer = np.zeros(body_sdf.size, dtype=bool)
        if thickness <= 0:
            return layer
        sdf = body_sdf.reshape(-1)
        index = np.flatnonzero((sdf > 0) & (sdf <= thickness))
        points = self._node_points(index)
        _, owner = nearest(cKDTree(body.pose(body.canonical_pose()).vertices), points)
        off_head = body.vertex_parts()[owner] != PART_NAMES.index("head")
        index, points = index[off_head], points[off_head]
        layer[index[self._hidden_from_the_first_photo(body, points)]] = True
        return layer

    def _hidden_from_the_first_photo(self, body: BodyModel, points: np.ndarray) -> np.ndarray:
        """(N,) bool: canonical ``points`` on the body's far side in the first photo's pose and camera that every
        other photo allows: there they lie on the far side too, or inside that photo's mask (a back photo shows
        how far the clothes stand off the back; outside its mask they are air)."""
        allowed = np.ones(len(points), dtype=bool)
        for k, view in enumerate(self.views.observed):
            hidden, posed = self._far_side_in(view, body, points)
            if k > 0:
                px, _, inside = view.camera.pixels(posed, view.person.shape)
                hidden[inside] |= view.person[px[inside, 1], px[inside, 0]]
            allowed &= hidden
        return allowed

    def on(self, name: str) -> bool:
        return self.weights[name] > 0

    def total(self, terms: Terms) -> torch.Tensor:
        """The step's loss: every term times its weight."""
        loss = torch.zeros((), device=self.device)
        for name, value in terms.items():
            loss = loss + self.weights[name] * value
        return loss

    # ---- the three kinds of step ------------------------------------------------------------------------
    def _reconstruction(self, render: torch.Tensor, target: torch.Tensor) -> Terms:
        terms: Terms = {}
        if self.on("perceptual"):
            terms["perceptual"] = self.perceptual(render, target)
        if self.on("mse"):
            terms["mse"] = mse(render, target)
        return terms

    def _tensor(self, array) -> torch.Tensor:
        return torch.as_tensor(np.asarray(array, dtype=np.float32), device=self.device)

    def stage1(self) -> Terms:
        """Reconstruct a patch of a template-textured body render (random background)."""
        rng, prior, poses = self.streams.sampling, self.views.prior, self.views.poses[1]
        pose = poses[int(rng.integers(len(poses)))]
        row, ci = prior.texture_rows[pose], int(rng.integers(len(self.views.ring)))
        size = min(self.cfg.crop_size, self.cfg.label_size)
        alpha = prior.alpha[row, ci].astype(np.float32) / 255.0
        x0, y0 = random_patch(rng, alpha > 0.5, size)
        cam = self.views.ring[ci].crop(x0, y0, size, size, size)
        bg = self.streams.background(self.device)
        out = self.renderer.render(cam, pose, bg)
        color = self._tensor(prior.color[row, ci, y0 : y0 + size, x0 : x0 + size]) / 255.0
        a = self._tensor(alpha[y0 : y0 + size, x0 : x0 + size])
        target = (color * a[..., None] + bg * (1 - a[..., None])).permute(2, 0, 1)[None]
        terms = self._reconstruction(out["rgb"], target)
        if self.on("alpha"):
            terms["alpha"] = mse(out["alpha"][0], a)
        return terms

    def input_patch(self) -> Terms:
        """Reconstruct a patch of an observed input photo, each equally often, in its own pose (random
        background). The first photo's outline counts too (the background outside its mask); another photo's
        only its colours (outside its mask the target is the render itself): its placement carries two body
        fits' error, and its outline carved the avatar the first photo shows (on ``open_jacket_tie`` front
        views lost 0.6 dB with it, 0.3 without)."""
        observed, rng = self.views.observed, self.streams.sampling
        view = observed[0] if len(observed) == 1 else observed[int(rng.integers(len(observed)))]
        size = min(self.cfg.crop_size, view.camera.width, view.camera.height)
        x0, y0 = random_patch(rng, view.person, size)
        cam = view.camera.crop(x0, y0, size, size, size)
        bg = self.streams.background(self.device)
        out = self.renderer.render(cam, view.pose, bg)
        m = view.mask[y0 : y0 + size, x0 : x0 + size]
        target = view.image[:, y0 : y0 + size, x0 : x0 + size] * m + bg[:, None, None] * (1 - m)
        if view is not observed[0]:  # another photo gives colour, not outline: its placement is less sure
            target = m * target + (1 - m) * out["rgb"][0].detach()
        self.photo_step = True
        return self._reconstruction(out["rgb"], target[None])

    def novel_view(self) -> Terms | None:
        """A hybrid-sampled novel (pose, camera) crop: silhouette, edge, opacity and semantic terms."""
        rng, prior, poses = self.streams.sampling, self.views.prior, self.views.poses[2]
        pose = poses[int(rng.integers(len(poses)))]
        row = prior.rows[pose]
        labels = prior.labels[row]
        min_px = min_part_pixels(self.cfg.part_min_pixels, self.views.ring[0])
        view = plan_novel_view(rng, prior.yaws[row], labels, min_px, self.cfg.hybrid_sampling)
        if view is None:
            return None
        size = self.cfg.crop_size
        cam = self.views.ring[view.camera].crop(*view.window[:2], view.window[2], view.window[2], size)
        out = self.renderer.render(cam, pose, torch.zeros(3, device=self.device))
        body = torch.as_tensor((labels[view.camera] >= 0).astype(np.float32))[None]
        mask_host = crop_image(body, view.window, size)[0].clamp(0, 1)
        mask = mask_host.to(self.device)
        terms: Terms = {}
        if self.on("silhouette"):
            terms["silhouette"] = silhouette_loss(out["alpha"][0], mask, soft=self.cfg.soft_silhouette)
        if self.on("edge"):
            with on_host():  # the crop of the host's labels
                dist = self._tensor(edge_distance(mask_host.numpy() > 0.5))
            terms["edge"] = edge_loss(out["alpha"], mask[None], dist[None])
        if self.on("opacity"):
            terms["opacity"] = opacity_entropy(out["alpha"])
        if self.encoder is not None and (self.on("semantic") or self.text_embedding is not None):
            ref = self._reference(view, pose)
            if ref is None:
                self.skipped_references += 1
            else:
                ref_img, ref_mask = ref
                part = crop_image(self._tensor(part_pixels(labels[view.camera], view.part))[None], view.window, size)
                emb = self.encoder(torch.cat([ref_img, out["rgb"]]), torch.cat([ref_mask, part]))
                if self.on("semantic"):
                    terms["semantic"] = semantic_loss(emb[:1].detach(), emb[1:])
                if self.text_embedding is not None:
                    terms["text"] = semantic_loss(self.text_embedding[None], emb[1:])
        return terms

    def _reference(self, view: NovelView, pose: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The semantic reference crop and its part mask: the input image's matching crop, or a no-grad
        render from the nearest side (rear views) or front (side views of the head) camera. With several input
        photos (observed or references only), the photo nearest the novel camera in yaw, where it lies within
        ``PHOTO_REFERENCE_DEG``, gives the crop (else the input image's, for an input reference)."""
        size = self.cfg.crop_size
        source = self.views.input
        photos = self.views.observed + self.views.references
        if len(photos) > 1:
            yaw = self.views.prior.yaws[self.views.prior.rows[pose], view.camera]
            gaps = [abs((p.yaw - yaw + 180.0) % 360.0 - 180.0) for p in photos]
            if min(gaps) <= PHOTO_REFERENCE_DEG:
                source, view = photos[int(np.argmin(gaps))], replace(view, reference="input")
        if view.reference == "render":
            mask = part_pixels(self.views.prior.labels[self.views.prior.rows[pose], view.ref_camera], view.part)
            window = crop_window(mask, view.part)
            if window is None:
                return None
            cam = self.views.ring[view.ref_camera].crop(*window[:2], window[2], window[2], size)
            black = torch.zeros(3, device=self.device)
            image = self.renderer.render(cam, pose, black, grad=False)["rgb"].detach()
        else:
            mask = part_pixels(source.labels, view.part)
            if mask.sum() < min_part_pixels(self.cfg.part_min_pixels, source.camera):
                return None
            window = crop_window(mask, view.part)
            image = crop_image(source.image, window, size)[None]
        return image, crop_image(self._tensor(mask)[None], window, size)

    def regularisers(self, stage: int, step: int) -> Terms:
        """Grid smoothness (both stages) and sparsity outside the body (stage 2), on one random block, and the
        mirror completion's unseen cells (stage 2). They read the grids through :attr:`regions`, whose
        gradients :meth:`backward` adds in."""
        f = self.field
        block = f.random_block(generator=self.streams.blocks)
        self.regions = GradRegions()
        terms: Terms = {}
        density = self.regions.block(f.density, block)
        if self.on("tv"):
            terms["tv"] = total_variation(density, self.regions.block(f.color, block))
        if stage == 2 and self.on("sparsity"):
            terms["sparsity"] = f.sparsity_loss(density, self.outside_body[block])
        if stage == 2 and self.completion is not None:
            cells = self.regions.rows(f.color, self.completion.cells)
            terms["mirror"] = self.completion.loss(f, step, cells)
        return terms

    def backward(self, loss: torch.Tensor) -> None:
        """Gradients of the step's ``loss`` (:meth:`total`) in every parameter's ``.grad``. A photo's patch leaves
        the colour of the completed cells on the body's far side alone (:attr:`behind`)."""
        loss.backward()
        if self.photo_step and self.behind is not None and self.field.color.grad is not None:
            self.field.color.grad.view(-1, 3).index_fill_(0, self.behind, 0.0)
        self.photo_step = False
        self.regions.add_gradients()
