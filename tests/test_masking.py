"""Masks without a given mask: colour likelihoods, the predicted mask's colour gate, the search when lost."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter

from surgtrack.geometry import make_T, project, span
from surgtrack.masking import (
    ColourModel,
    grow_region,
    predict_mask,
    render_box,
    render_depth,
    search_regions,
    seen_past,
    silhouette_core,
    silhouette_iou,
)

K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
GREY, GREEN, SKIN, BLUE = (150, 150, 155), (40, 140, 60), (220, 170, 140), (30, 40, 200)


def scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grey bar (the instrument) at 0.3 m on a green drape at 0.5 m; rgb, depth, mask."""
    rgb = np.empty((120, 160, 3), np.uint8)
    rgb[:] = GREEN
    depth = np.full((120, 160), 0.5, np.float32)
    mask = np.zeros((120, 160), bool)
    mask[50:70, 30:130] = True
    rgb[mask] = GREY
    depth[mask] = 0.3
    return rgb, depth, mask


def bar_points(mask: np.ndarray, depth: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(mask)
    z = depth[v, u]
    return np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)


def test_colour_posterior_separates_instrument_from_surroundings():
    rgb, _, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    probe = np.array([[GREY, GREEN, BLUE]], np.uint8)
    p = colours.posterior(probe)[0]
    assert p[0] > 0.9 and p[1] < 0.1
    assert abs(p[2] - 0.5) < 1e-3  # a colour neither side has seen decides nothing


def test_predicted_mask_does_not_grow_into_a_hand_at_the_instruments_depth():
    rgb, depth, mask = scene()
    seen = rgb.copy()
    seen[40:80, 140:150] = SKIN  # the first frame shows the hand near the bar
    colours = ColourModel()
    colours.learn(seen, mask)
    # next frame: the hand touches the bar's end at the bar's depth, and the bar itself is unchanged
    rgb2, depth2 = rgb.copy(), depth.copy()
    hand = np.zeros_like(mask)
    hand[45:75, 130:134] = True
    rgb2[hand], depth2[hand] = SKIN, 0.3
    points = bar_points(mask, depth)
    pose = np.eye(4)
    plain = predict_mask(points, pose, K, depth2, 6, 0.01)
    gated = predict_mask(points, pose, K, depth2, 6, 0.01, rgb2, colours, 0.25)
    assert (plain & hand).sum() > 50  # depth alone takes the touching hand in
    assert not (gated & hand).any()
    assert (gated & mask).sum() >= 0.95 * mask.sum()  # the instrument itself is all kept


def test_a_hand_once_seen_in_front_of_the_instrument_stays_out_of_the_mask_beside_it():
    """A glove the first frame did not show decides nothing (posterior 0.5) and gets into the mask where it touches
    the instrument at its depth; once its pixels were seen in front of the instrument (`add_surroundings`), the
    colour gate keeps it out, and the instrument itself is still all kept."""
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)  # no hand in the first frame
    rgb2, depth2 = rgb.copy(), depth.copy()
    hand = np.zeros_like(mask)
    hand[45:75, 130:134] = True
    rgb2[hand], depth2[hand] = SKIN, 0.3
    points = bar_points(mask, depth)

    def gated() -> np.ndarray:
        return predict_mask(points, np.eye(4), K, depth2, 6, 0.01, rgb2, colours, 0.25)

    assert (gated() & hand).sum() > 50
    front = np.zeros_like(mask)
    front[50:70, 60:70] = True  # where the hand lay across the bar, in front of it, in an earlier frame
    rgb3 = rgb.copy()
    rgb3[front] = SKIN
    colours.add_surroundings(rgb3, front)
    assert not (gated() & hand).any()
    assert (gated() & mask).sum() >= 0.95 * mask.sum()


def later_frame(parts: list[tuple[tuple[slice, slice], float]]) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """A frame of `scene`'s drape with grey ``parts`` (image region, depth) on it: rgb, depth, the parts' masks."""
    rgb, depth, _ = scene()
    rgb[:] = GREEN
    depth[:] = 0.5
    masks = []
    for region, z in parts:
        masks.append(np.zeros(depth.shape, bool))
        masks[-1][region] = True
        rgb[region] = GREY
        depth[region] = z
    return rgb, depth, masks


def test_predicted_mask_leaves_out_a_finger_on_the_instrument_but_not_an_instrument_that_came_nearer():
    rgb, depth, mask = scene()
    points = bar_points(mask, depth)
    pose = np.eye(4)
    # next frame: a finger lies across the bar, 6 mm in front of it
    depth2 = depth.copy()
    finger = np.zeros_like(mask)
    finger[44:76, 70:78] = True
    depth2[finger] = 0.294
    symmetric = predict_mask(points, pose, K, depth2, 4, 0.01)
    tight = predict_mask(points, pose, K, depth2, 4, 0.01, front_tol=0.004)
    assert (symmetric & finger).sum() > 0.9 * (finger & mask).sum()  # 1 cm either way takes the finger in
    assert not (tight & finger).any()
    assert (tight & mask & ~finger).sum() == (mask & ~finger).sum()  # the bar beside it is all kept
    # the whole bar 6 mm nearer than predicted (it moved): the tight bound would lose it, so it is not applied
    nearer = np.where(mask, np.float32(0.294), depth)
    assert predict_mask(points, pose, K, nearer, 4, 0.01, front_tol=0.004)[mask].all()


def test_search_finds_the_nearest_instrument_coloured_regions_of_plausible_size():
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    # the bar has moved to the top left; a big grey tray lies bottom right; a few grey speckles
    rgb2, depth2, (moved, tray) = later_frame([(np.s_[10:30, 10:110], 0.32), (np.s_[70:120, 40:160], 0.45)])
    rgb2[5, 150] = GREY
    last = np.array([0.0, 0.0, 0.3])  # last seen at the image centre, 0.3 m
    found = search_regions(colours.posterior(rgb2), depth2, K, last, 0.5, 0.6, (40, 2 * int(mask.sum())), n=3)
    assert len(found) == 1 and (found[0] == moved).all()  # the tray is too big to be the instrument
    both = search_regions(colours.posterior(rgb2), depth2, K, last, 0.5, 0.6, (40, 6000), n=3)
    assert len(both) == 2 and (both[0] == moved).all() and (both[1] == tray).all()  # nearest first
    assert not search_regions(colours.posterior(rgb2), depth2, K, last, 0.05, 0.6, (40, 6000))  # out of reach


def test_search_skips_a_region_far_wider_than_the_instrument_however_few_its_pixels():
    """A grey wall 3 m away shows in fewer pixels than the bar at 0.3 m but spans half a metre: by pixel count it
    could be the instrument, by its width (`geometry.span`) it cannot. The bar's top row reads the drape far behind
    it (edge pixels of a real sensor), which does not make the bar any wider."""
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    rgb2, depth2, (moved, wall) = later_frame([(np.s_[10:30, 10:110], 0.32), (np.s_[90:120, 120:160], 3.0)])
    depth2[10, 10:110] = 2.5  # 5 % of the bar's pixels
    bar = span(bar_points(mask, depth))
    assert wall.sum() < moved.sum() and span(bar_points(wall, depth2)) > 3 * bar
    assert span(bar_points(moved, depth2)) > 3 * bar  # in 3D, the bar's edge row alone sets its span
    last = np.array([0.0, 0.0, 0.3])
    posterior = colours.posterior(rgb2)
    assert len(search_regions(posterior, depth2, K, last, 5.0, 0.6, (40, 6000), n=3)) == 2
    found = search_regions(posterior, depth2, K, last, 5.0, 0.6, (40, 6000), n=3, max_span=3 * bar)
    assert len(found) == 1 and (found[0] == moved).all()


def test_search_cuts_a_merged_region_where_the_depth_jumps():
    """The instrument's colour region runs into a nearer hand of a similar colour: too big as a whole, the region
    is cut at the depth step and at missing depth between them, and the instrument's part is found, even when a
    small look-alike elsewhere is of a plausible size as it is."""
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    # the hand touches the bar's end, 8 cm nearer; a fingertip-sized grey patch lies nearer the last position
    parts = [(np.s_[50:70, 10:115], 0.32), (np.s_[:, 115:], 0.24), (np.s_[5:15, 70:80], 0.3)]
    rgb2, depth2, (bar, hand, patch) = later_frame(parts)
    depth2[60, 60:64] = 0.0  # dropouts on the bar stay inside it
    depth2[30:40, 110:120] = 0.0  # and at the hand's edge
    last = np.array([0.0, -0.03, 0.3])
    pixels = (40, 3 * int(mask.sum()))
    found = search_regions(colours.posterior(rgb2), depth2, K, last, 0.5, 0.6, pixels, n=3)
    assert any((region == patch).all() for region in found)
    (cut,) = [region for region in found if (region & bar).any()]
    assert cut.sum() > 0.9 * (bar & (depth2 > 0)).sum() and not (cut & hand).any()
    uncut = search_regions(colours.posterior(rgb2), depth2, K, last, 0.5, 0.6, pixels, n=3, depth_step=0.1)
    assert any((region == patch).all() for region in uncut) and not any((region & bar).any() for region in uncut)


def test_a_search_region_grows_into_middling_colours_within_its_reach_but_not_onto_the_drape():
    """The bar's grey shows only on its left end, the rest of it is a colour the first frame did not show
    (posterior near 0.5), and a patch of that colour lies on the drape beside it, a depth jump away."""
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    rgb2, depth2, (bar, patch) = later_frame([(np.s_[50:70, 30:130], 0.3), (np.s_[70:80, 60:90], 0.5)])
    rgb2[:, 50:] = np.where((bar | patch)[:, 50:, None], BLUE, rgb2[:, 50:])
    posterior = colours.posterior(rgb2)
    assert 0.4 <= posterior[bar].min() and posterior[patch].max() < 0.6 and posterior[~(bar | patch)].max() < 0.4
    grey = bar & (posterior >= 0.6)
    near = bar.copy()
    near[:, 65:] = False  # within 15 px of the grey end
    assert (grow_region(grey, depth2, posterior, 0.4, 15, 0.01) == near).all()
    assert (grow_region(grey, depth2, posterior, 0.4, 100, 0.01) == bar).all()


def test_predicted_mask_leaves_out_a_glove_inside_the_outline_whose_colour_the_first_frame_saw_further_away():
    """A gloved finger lies on the bar, within the depth window, inside the rendered outline. The first frame showed
    the glove 60 pixels from the bar, beyond a narrow ring: only the wider surroundings learn its colour, and only
    the gate inside the outline cuts it."""
    rgb, depth, mask = scene()
    seen = rgb.copy()
    seen[5:15, 30:130] = SKIN  # the first frame: the glove well above the bar
    rgb2, depth2 = rgb.copy(), depth.copy()
    finger = np.zeros_like(mask)
    finger[50:70, 70:78] = True  # next frame: a finger on the bar, 2 mm in front of it
    rgb2[finger], depth2[finger] = SKIN, 0.298
    points = bar_points(mask, depth)
    pose = np.eye(4)
    for ring, cut in ((30, False), (120, True)):
        colours = ColourModel(ring=ring)
        colours.learn(seen, mask)
        gated = predict_mask(points, pose, K, depth2, 4, 0.01, rgb2, colours, 0.1, 0.004, inside_posterior=0.1)
        assert (gated & mask & ~finger).sum() == (mask & ~finger).sum()  # the bar beside it is all kept
        assert (gated & finger).any() != cut
    colours = ColourModel(ring=120)
    colours.learn(seen, mask)
    ungated = predict_mask(points, pose, K, depth2, 4, 0.01, rgb2, colours, 0.1, 0.004)
    assert (ungated & finger).sum() > 0.8 * finger.sum()  # without the gate inside, only the rim is cut


def test_silhouette_agreement_tells_the_whole_instrument_from_a_piece_of_it():
    """The model's silhouette at a pose agrees with the bar's own region, not with a fingertip-sized piece of it
    that one part of the model would fit just as well."""
    _, depth, mask = scene()
    points = bar_points(mask, depth)
    whole = silhouette_iou(points, np.eye(4), K, mask)
    piece = mask.copy()
    piece[:, 50:] = False  # 20 of the bar's 100 columns
    assert whole > 0.8
    assert silhouette_iou(points, np.eye(4), K, piece) < 0.25
    shifted = np.eye(4)
    shifted[1, 3] = 0.05  # the pose 5 cm off across the bar: its silhouette lands beside it
    assert silhouette_iou(points, shifted, K, mask) < 0.1


def test_predicted_mask_grows_along_a_shaft_the_model_has_not_seen_but_not_onto_what_lies_behind_it():
    """The model knows the bar's left half; the frame shows the whole bar, sloping away, with a grey patch on the
    drape behind it touching its end. The grown mask takes the rest of the bar and stops at the depth jump; growth
    spilling over far more than the mask (a grey tray at the bar's depth) is not taken."""
    rgb, depth, mask = scene()
    colours = ColourModel()
    colours.learn(rgb, mask)
    rgb2, depth2, (bar, patch) = later_frame([(np.s_[50:70, 30:150], 0.3), (np.s_[40:80, 150:160], 0.5)])
    depth2[bar] += np.linspace(0.0, 0.05, 120)[None, :].repeat(20, 0).ravel()  # 0.4 mm per pixel further away
    known = mask.copy()
    known[:, 80:] = False
    points = bar_points(known, depth2)
    plain = predict_mask(points, np.eye(4), K, depth2, 4, 0.01, rgb2, colours, 0.25)
    grown = predict_mask(points, np.eye(4), K, depth2, 4, 0.01, rgb2, colours, 0.25, grow_posterior=0.6)
    assert (plain & bar).sum() < 0.6 * bar.sum()
    assert (grown & bar).sum() >= 0.95 * bar.sum() and not (grown & patch).any()
    rgb3, depth3, (bar, tray) = later_frame([(np.s_[50:70, 30:150], 0.3), (np.s_[70:120, :], 0.3)])
    spilled = predict_mask(points, np.eye(4), K, depth3, 4, 0.01, rgb3, colours, 0.25, grow_posterior=0.6)
    assert (spilled == predict_mask(points, np.eye(4), K, depth3, 4, 0.01, rgb3, colours, 0.25)).all()


def test_seen_past_is_the_share_of_the_silhouette_the_camera_saw_through():
    """0 where the frame's depth is the model's, 1 where it lies behind it everywhere, about a half where behind on
    one half, and an occluder in front of the model is left out rather than counted as seen through."""
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    g = np.linspace(-0.03, 0.03, 61)
    plate = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    points = np.column_stack([plate, np.zeros(len(plate))])
    pose = make_T(np.eye(3), np.array([0.0, 0.0, 0.4]))
    model = render_depth(points, pose, K, (240, 320))
    assert seen_past(points, pose, K, model, 0.01) == 0.0
    assert seen_past(points, pose, K, np.where(model > 0, model + 0.05, 0.6), 0.01) == 1.0
    half = np.where(model > 0, model, 0.6)
    half[:, 160:] += 0.05
    assert 0.4 < seen_past(points, pose, K, half, 0.01) < 0.6
    hand = half.copy()
    hand[:, 160:] = np.where(model[:, 160:] > 0, model[:, 160:] - 0.05, 0.6)  # a hand in front of that half
    assert seen_past(points, pose, K, hand, 0.01) == 0.0


def test_render_depth_is_the_nearest_point_within_the_splat_even_at_the_frame_border():
    """Each pixel holds the nearest model depth within ``splat`` pixels (0 where none), also where the model runs
    off the frame: the same as a z-buffer of the whole frame under a min filter."""
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    rng = np.random.default_rng(3)
    points = rng.normal(size=(3000, 3)) * [0.08, 0.01, 0.01]  # a shaft longer than the frame is wide
    pose = make_T(np.eye(3), np.array([0.05, 0.0, 0.3]))
    depth = render_depth(points, pose, K, (240, 320))
    uv, z = project(points + pose[:3, 3], K)
    u, v = np.round(uv).astype(int).T
    inside = (u >= 0) & (u < 320) & (v >= 0) & (v < 240)
    assert 0 < inside.sum() < len(points)
    full = np.full((240, 320), np.inf, np.float32)
    np.minimum.at(full, (v[inside], u[inside]), z[inside].astype(np.float32))
    full = minimum_filter(full, size=5, mode="constant", cval=np.inf)
    assert np.array_equal(depth, np.where(np.isfinite(full), full, 0))


def test_seen_past_worked_in_the_renders_box_is_that_of_the_whole_frame():
    """The check renders only the box around the model (grown for the silhouette's erosion): on a shaft running
    off the frame's edge, with the background behind part of it, it reads as on the whole frame."""
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    rng = np.random.default_rng(3)
    points = rng.normal(size=(3000, 3)) * [0.08, 0.01, 0.01]
    pose = make_T(np.eye(3), np.array([0.05, 0.0, 0.3]))
    whole = render_depth(points, pose, K, (240, 320))
    box, crop = render_box(points, pose, K, (240, 320), pad=3)
    assert box[1].stop == 320 and np.array_equal(whole[box], crop) and whole.sum() == crop.sum()
    depth = np.where(whole > 0, whole, 0.6)
    depth[:, 250:] += 0.05  # seen through where the shaft leaves the frame
    depth[100:110, :200] = 0.1  # an occluder across it
    core = silhouette_core(whole) & (depth > 0) & (depth > whole - 0.01)
    expected = (depth[core] > whole[core] + 0.01).mean()
    assert 0.1 < expected < 0.5 and seen_past(points, pose, K, depth, 0.01) == expected
    assert seen_past(points, make_T(np.eye(3), np.array([0.0, 0.0, -0.3])), K, depth, 0.01) == 0.0  # behind


def test_silhouette_iou_worked_in_the_renders_box_is_that_of_the_whole_frame():
    """The IoU renders only the model's box: a mask reaching far beyond it (a uint8 mask, as read from a PNG), a
    model running off the frame's edge and a model behind the camera read as on the whole frame."""
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    rng = np.random.default_rng(3)
    points = rng.normal(size=(3000, 3)) * [0.08, 0.01, 0.01]
    pose = make_T(np.eye(3), np.array([0.05, 0.0, 0.3]))
    outline = render_depth(points, pose, K, (240, 320)) > 0
    mask = np.zeros((240, 320), np.uint8)
    mask[110:130, 100:320] = 255  # over part of the shaft
    mask[0:40, 0:60] = 7  # far from the model's box
    expected = (outline & (mask > 0)).sum() / (outline | (mask > 0)).sum()
    assert 0.05 < expected < 0.9
    assert silhouette_iou(points, pose, K, mask) == expected
    assert silhouette_iou(points, make_T(np.eye(3), np.array([0.0, 0.0, -0.3])), K, mask) == 0.0
