"""Named synthetic people for the benchmarks: clothes and postures of real people, which seeds alone do not draw.

Each is a seed (phenotype, skin, colours, as ``elicit synth --seed`` draws them) and the changes to the outfit it
draws (``synth.Outfit``'s fields). Real clothes are mostly plain at the back and carry their details on the
front (an open jacket over a shirt and tie, a logo, a placket); people hold things, cross their arms, sit.
"""

from __future__ import annotations

WHITE, CHARCOAL, NAVY = (0.9, 0.9, 0.88), (0.12, 0.12, 0.14), (0.1, 0.12, 0.22)
PLAIN = {"shirt_pattern": "solid", "back_print": "none"}  # a top that is the same colour all round
PEOPLE: dict[str, tuple[int, dict]] = {
    "open_jacket_tie": (21, {**PLAIN, "shirt": WHITE, "shirt_alt": WHITE, "jacket": (0.35, 0.3, 0.25),
                             "tie": (0.55, 0.1, 0.12), "long_sleeves": True, "loose_top": True, "skirt": False}),
    "front_details": (22, {**PLAIN, "front_detail": True, "skirt": False}),
    "held_folder": (23, {**PLAIN, "held_object": (0.75, 0.72, 0.6), "posture": "holding", "skirt": False}),
    "arms_crossed": (24, {**PLAIN, "posture": "arms_crossed", "long_sleeves": True}),
    "hands_in_pockets": (25, {**PLAIN, "posture": "hands_in_pockets", "skirt": False, "shorts": False}),
    "short_dark_hair": (26, {"hair": (0.06, 0.05, 0.04), "hair_long": False, "hair_volume": 0.0}),
    "long_hair": (27, {**PLAIN, "hair_long": True, "hair_down_back": True, "hair_volume": 0.03}),
    "dark_suit": (28, {**PLAIN, "shirt": WHITE, "shirt_alt": WHITE, "jacket": CHARCOAL, "jacket_open": False,
                       "tie": NAVY, "trousers": CHARCOAL, "trouser_pattern": "solid", "shoes": (0.05, 0.04, 0.04),
                       "long_sleeves": True, "loose_top": True, "skirt": False, "shorts": False}),
    "seated": (29, {"posture": "seated", "skirt": False}),
    "legs_crossed": (30, {"posture": "legs_crossed", "skirt": False}),
    "arms_raised": (31, {"posture": "arms_raised"}),
    "arms_forward": (32, {"posture": "arms_forward"}),
}  # fmt: skip
