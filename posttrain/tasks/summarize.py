"""tiny-summarize: seeded synthetic documents, reference summaries, a gold scorer and the
gold preference "length first, then quality" (seed exercise §16 E6).

Pure Python (no torch): the task is data plus exact scoring rules, usable from tests,
scripts and the verifier layer alike.

    from posttrain.tasks import summarize
    examples = summarize.make_examples(1000, seed=0, split="train")
    summarize.gold_quality(examples[0]["meta"], " Milo the red fox eats berries.")

Documents
---------
Two kinds, chosen 50/50, each 3-6 short sentences over a closed vocabulary (~300 words):

- ``animal``: an animal with a name, colour and species, plus 1-3 of: its home
  (region + habitat), its food, its young ("has three cubs").
- ``news``: an event (actor, verb, object: "The council opened a new library."), plus
  1-3 of: the town, the weekday, a number ("The library has twelve rooms.").

The subject sentence (animal identity / news event) comes first; the other key facts and
1-4 filler sentences follow in random order. Fillers are never key facts: habits, weather,
crowds, and *distractors* that carry other values of the same kinds (another named animal
"lives nearby", other food "grows near there", a person who "said it was good", a crowd
size like "forty"). So every document has 2-4 key facts and 3-6 sentences, and a model has
to pick the key facts out, not copy the document.

Example format (JSON-serialisable, saved as JSONL)::

    {"prompt": "Document: <3-6 sentences>\\nSummary:",
     "completion": " <reference summary>",          # starts with a space
     "meta": {...}}                                  # what the gold scorer needs, below

``meta`` keys: ``task`` ("tiny-summarize"), ``kind`` ("animal" | "news"), ``subject``
(the values that fix the split), ``facts`` (list of ``{"name", "keys"}``), ``entities``
(names in the document), ``doc_words`` (sorted normalised words of the document),
``band`` ([L_lo, L_hi]), ``concise_summary`` and ``concise_length``, ``style``.

Reference summaries (deliberately mixed, so an SFT model has spread in length and quality)
------------------------------------------------------------------------------------------
- ``concise`` (30%): one sentence stating every key fact, e.g.
  "Milo the red fox lives in the north forest, eats berries and has three cubs."
  Always in the band, gold quality 1.0.
- ``verbose`` (45%): the concise sentence followed by 1-2 filler sentences of the
  document restated. Complete and faithful (quality 1.0) but 4+ words over the band.
- ``terse`` (25%): the concise sentence with one non-subject key fact dropped. Quality
  below 1 (coverage (k-1)/k); in the band when the dropped fact was short, under it
  otherwise.
The style is drawn independently of the document, so the prompt does not predict it.

Splits
------
``make_examples(n, seed, split)`` is deterministic in (n, seed, split), and a prefix of a
longer call with the same seed and split. Train and eval are disjoint by construction:
every document states its subject first (animal: name + colour + species; news: actor +
verb + object), and a SHA-1 of that subject assigns it to exactly one split (about 20% of
subjects to eval); each split draws from its own random stream. The vocabulary is shared,
so eval tests new combinations, not unseen words.

Gold quality (``gold_quality``, ``gold_breakdown``) -- exact rules
------------------------------------------------------------------
Words are ``re.findall(r"[a-z0-9]+", text.lower())``; the summary is stripped first.

- empty (no words): quality 0.
- coverage C = covered facts / key facts; a fact is covered when all its ``keys`` are
  among the summary's words (animal identity: name, colour, species; home: region,
  habitat; food: food; young: number, young noun; news event: actor, verb, object;
  place: town; day: weekday; number: number, unit).
- faithfulness F = max(0, 1 - 0.5 * I), I = number of distinct *invented* words: summary
  words that are neither in the document nor in the small glue list ``GLUE`` (articles,
  "and", "lives", "eats", "has", "new", ...). A name, colour, number or town not in the
  document is invented, and so is any out-of-vocabulary junk word.
- form: E = ends with ".", K = starts with a capital letter.
- repetition factor R = 1/4 if the summary is *degenerate* (some word 4-gram occurs twice,
  or a word occurs 3 times in a row), else 1.

    quality = F * R * (0.70 * C + 0.15 * E + 0.15 * K)        in [0, 1]

Computed exactly (fractions), returned as float.

Gold preference: length first, then quality
-------------------------------------------
Each example has a length band [L_lo, L_hi] = [Lc - 2, Lc + 2] words, where Lc is the word
length of the concise reference (Lc >= 6, so L_lo >= 4). The distance of a summary of n
words is d = max(0, L_lo - n, n - L_hi) (0 inside the band).

    gold_key(meta, s) = (-d, round(quality, 2))       larger is better
    gold_prefer(meta, a, b) = +1 if key(a) > key(b), -1 if key(a) < key(b), 0 if equal

i.e. the summary closer to the band wins; at equal distance the higher quality wins, where
qualities that round to the same hundredth tie (the epsilon; quality takes a few discrete
values, so this only absorbs rounding); otherwise tie. ``win_rate`` counts a tie as half a
win.

Why this resists the obvious hacks: an empty summary has d = L_lo >= 4, never in band; a
degenerate one scores at most 0.25; garbage of the right length has C = 0 (quality <= 0.3,
and invented words cut it further) so it loses to any in-band summary with the facts.
Known gap (string-matching gold): a keyword list padded with document words to the band
length scores like a sentence; the glue/invented rule and the 4-gram rule limit the
padding to words of the document.

With this band the references straddle it: over 3,000 train examples 42% are in band,
45% too long (all verbose), 13% too short (terse); mean gold quality 0.94, mean length
14.3 words. An ideal policy -- the concise summary every time -- wins 85% against the
references (it ties the concise 30% and beats the rest), so an SFT model that imitates
them leaves clear room for preference learning.
"""
from __future__ import annotations

import hashlib
import random
import re
from fractions import Fraction
from typing import Any, Literal, Sequence

TASK_NAME = NAME = "tiny-summarize"
VERIFIER = None  # no verifiable answers: the gold signal is gold_quality / gold_key
GOLD_METRICS = {"quality": "mean_quality", "in_band": "frac_in_band", "length": "mean_length"}
PROMPT_TEMPLATE = "Document: {document}\nSummary:"

STYLE_WEIGHTS = {"concise": 0.30, "verbose": 0.45, "terse": 0.25}
BAND_BELOW = 2  # L_lo = Lc - BAND_BELOW
BAND_ABOVE = 2  # L_hi = Lc + BAND_ABOVE
EVAL_FRACTION_BUCKETS = 5  # a subject goes to eval when sha1(subject) % 5 == 0 (~20%)

W_COVERAGE = Fraction(70, 100)
W_PERIOD = Fraction(15, 100)
W_CAPITAL = Fraction(15, 100)
INVENTED_PENALTY = Fraction(1, 2)  # per distinct invented word
DEGENERATE_FACTOR = Fraction(1, 4)
REPEAT_NGRAM = 4
QUALITY_DECIMALS = 2  # tie-break resolution of the preference

# --- the closed world -------------------------------------------------------------------

NAMES = [
    "Milo", "Pip", "Luna", "Rosa", "Finn", "Nora", "Otto", "Ivy", "Leo", "Mia",
    "Ben", "Zoe", "Max", "Ada", "Tom", "Lily", "Sam", "Eva", "Hugo", "Iris",
    "Jack", "Kira", "Remy", "Tess", "Olga", "Nico", "Bea", "Cal", "Dora", "Eli",
    "Fay", "Gus", "Hana", "Ivo", "Juno", "Kai", "Lars", "Maya", "Ned", "Opal",
]
COLOURS = ["red", "brown", "grey", "white", "black", "golden", "spotted", "striped"]
SPECIES_YOUNG = {
    "fox": "cubs", "owl": "chicks", "rabbit": "kits", "bear": "cubs", "deer": "fawns",
    "wolf": "pups", "otter": "pups", "badger": "cubs", "mouse": "pups", "duck": "ducklings",
    "frog": "tadpoles", "cat": "kittens",
}
REGIONS = ["north", "south", "east", "west", "old", "deep"]
HABITATS = ["forest", "river", "hill", "valley", "meadow", "lake", "cave", "marsh"]
FOODS = ["berries", "nuts", "seeds", "apples", "carrots", "grass", "leaves", "mushrooms", "plums", "corn"]
NUMBERS = ["two", "three", "four", "five", "six", "seven", "eight", "nine", "ten", "eleven", "twelve"]
CROWDS = ["twenty", "thirty", "forty", "fifty", "sixty", "seventy", "eighty"]
DAYS = ["Monday", "Tuesday", "Wednesday", "Thursday", "Friday", "Saturday", "Sunday"]
TOWNS = [
    "Oakton", "Millbrook", "Riverby", "Stonefield", "Ashford", "Elmwood", "Fairport", "Greenvale",
    "Hillcrest", "Lakeside", "Maplewood", "Northgate", "Pinecrest", "Redbank", "Sandhill", "Westbury",
]
ACTORS = ["council", "school", "club", "bakery", "farm", "museum", "hospital", "theatre", "zoo", "college"]
VERBS = ["opened", "built", "planned", "finished"]
OBJECT_UNITS = {
    "park": "trees", "bridge": "lamps", "garden": "beds", "market": "stalls", "playground": "swings",
    "hall": "seats", "shop": "shelves", "pool": "lanes", "library": "rooms", "cafe": "tables",
}

# Words a summary may use without taking them from the document. Nothing here is a value
# (name, colour, number, place, ...), so an invented value is never excused.
GLUE = frozenset(
    "a an the and in on at of with by to is was it its that who which also lives eats has new named called".split()
)

# Filler templates. Kept free of region/habitat/town words so restating one never repeats
# a 4-gram of the concise sentence.
HABITS = ["sleep in the sun", "swim in cold water", "climb tall trees", "sing at night",
          "run in the grass", "play with sticks"]
SEASONS = ["spring", "summer", "autumn", "winter"]
TEMPERS = ["warm", "cool", "short", "long"]
NIGHTS = ["quiet", "cold", "long", "dark", "calm"]
MOODS = ["happy", "glad", "proud", "surprised"]
WEATHER = ["cold", "warm", "sunny", "windy", "rainy"]
OPINIONS = ["very good", "a fine idea", "long overdue", "a big help"]


def _words(text: str) -> list[str]:
    return re.findall(r"[a-z0-9]+", text.lower())


VALUE_WORDS = frozenset(
    w
    for group in (NAMES, COLOURS, list(SPECIES_YOUNG), list(SPECIES_YOUNG.values()), REGIONS, HABITATS,
                  FOODS, NUMBERS, CROWDS, DAYS, TOWNS, ACTORS, VERBS, list(OBJECT_UNITS),
                  list(OBJECT_UNITS.values()))
    for item in group
    for w in _words(item)
)
assert not (GLUE & VALUE_WORDS), f"GLUE must hold no value words: {sorted(GLUE & VALUE_WORDS)}"


# --- generation ---------------------------------------------------------------------------

def _split_of(subject: Sequence[str]) -> str:
    digest = hashlib.sha1("|".join(subject).encode()).hexdigest()
    return "eval" if int(digest[:8], 16) % EVAL_FRACTION_BUCKETS == 0 else "train"


def _join_predicates(subject: str, preds: list[str]) -> str:
    if len(preds) == 1:
        return f"{subject} {preds[0]}."
    return f"{subject} {', '.join(preds[:-1])} and {preds[-1]}."


def _animal(rng: random.Random, split: str) -> dict[str, Any]:
    while True:
        name, colour, species = rng.choice(NAMES), rng.choice(COLOURS), rng.choice(list(SPECIES_YOUNG))
        if _split_of(("animal", name, colour, species)) == split:
            break
    young = SPECIES_YOUNG[species]
    region, habitat, food, number = rng.choice(REGIONS), rng.choice(HABITATS), rng.choice(FOODS), rng.choice(NUMBERS)
    k = rng.choice([2, 3, 4])
    optional = rng.sample(["home", "food", "young"], k - 1)
    fact_order = [f for f in ("home", "food", "young") if f in optional]  # canonical order in summaries

    sentences = {
        "identity": rng.choice([
            f"{name} is a {colour} {species}.",
            f"There is a {colour} {species} named {name}.",
            f"This story is about a {colour} {species} called {name}.",
        ]),
        "home": rng.choice([
            f"{name} lives in the {region} {habitat}.",
            f"The home of {name} is in the {region} {habitat}.",
            f"{name} has a home in the {region} {habitat}.",
        ]),
        "food": rng.choice([
            f"{name} eats {food}.",
            f"Every day {name} looks for {food} to eat.",
            f"The favourite food of {name} is {food}.",
        ]),
        "young": rng.choice([
            f"{name} has {number} {young}.",
            f"{name} takes care of {number} {young}.",
        ]),
    }
    keys = {
        "identity": [name, colour, species],
        "home": [region, habitat],
        "food": [food],
        "young": [number, young],
    }
    predicates = {
        "home": f"lives in the {region} {habitat}",
        "food": f"eats {food}",
        "young": f"has {number} {young}",
    }
    other_name = rng.choice([n for n in NAMES if n != name])
    other_colour = rng.choice([c for c in COLOURS if c != colour])
    other_species = rng.choice([s for s in SPECIES_YOUNG if s != species])
    other_food = rng.choice([f for f in FOODS if f != food])
    night = rng.sample(NIGHTS, 2)
    fillers = [
        f"{name} likes to {rng.choice(HABITS)}.",
        f"The days are {rng.choice(TEMPERS)} in {rng.choice(SEASONS)}.",
        "Many birds sing in the trees nearby.",
        f"A {other_colour} {other_species} named {other_name} lives nearby.",
        f"Some {other_food} grow near there.",
        f"The nights are {night[0]} and {night[1]}.",
    ]

    def concise(facts: list[str]) -> str:
        subject = f"{name} the {colour} {species}"
        if not facts:
            return f"{name} is a {colour} {species}."
        return _join_predicates(subject, [predicates[f] for f in facts])

    return _assemble(rng, "animal", ("animal", name, colour, species), "identity", fact_order,
                     sentences, keys, fillers, concise, entities=[name, other_name])


def _news(rng: random.Random, split: str) -> dict[str, Any]:
    while True:
        actor, verb, obj = rng.choice(ACTORS), rng.choice(VERBS), rng.choice(list(OBJECT_UNITS))
        if _split_of(("news", actor, verb, obj)) == split:
            break
    unit = OBJECT_UNITS[obj]
    town, day, number = rng.choice(TOWNS), rng.choice(DAYS), rng.choice(NUMBERS)
    k = rng.choice([2, 3, 4])
    optional = rng.sample(["place", "day", "number"], k - 1)
    fact_order = [f for f in ("place", "day", "number") if f in optional]

    sentences = {
        "event": rng.choice([
            f"The {actor} {verb} a new {obj}.",
            f"A new {obj} was {verb} by the {actor}.",
        ]),
        "place": rng.choice([
            f"It is in {town}.",
            f"This happened in {town}.",
            f"The {obj} is in {town}.",
        ]),
        "day": rng.choice([
            f"The news came on {day}.",
            f"This was on {day}.",
            f"It was shown to the public on {day}.",
        ]),
        "number": rng.choice([
            f"The {obj} has {number} {unit}.",
            f"There are {number} {unit} in the {obj}.",
        ]),
    }
    keys = {
        "event": [actor, verb, obj],
        "place": [town],
        "day": [day],
        "number": [number, unit],
    }
    person = rng.choice(NAMES)
    fillers = [
        f"People in the town were {rng.choice(MOODS)}.",
        f"The weather was {rng.choice(WEATHER)} that day.",
        f"About {rng.choice(CROWDS)} people came to see it.",
        f"A {rng.choice(['woman', 'man'])} named {person} said it was {rng.choice(OPINIONS)}.",
        "Children played nearby all afternoon.",
        f"The {actor} wants to do more next year.",
    ]

    def concise(facts: list[str]) -> str:
        text = f"the {actor}"
        if "place" in facts:
            text += f" in {town}"
        text += f" {verb} a new {obj}"
        if "number" in facts:
            text += f" with {number} {unit}"
        if "day" in facts:
            text = f"on {day} " + text
        return text[0].upper() + text[1:] + "."

    return _assemble(rng, "news", ("news", actor, verb, obj), "event", fact_order,
                     sentences, keys, fillers, concise, entities=[person])


def _assemble(rng, kind, subject, subject_fact, fact_order, sentences, keys, fillers, concise, entities):
    k = 1 + len(fact_order)
    n_fill = rng.randint(max(1, 3 - k), 6 - k)
    chosen_fillers = rng.sample(fillers, n_fill)
    body = [sentences[f] for f in fact_order] + chosen_fillers
    rng.shuffle(body)
    document = " ".join([sentences[subject_fact]] + body)

    concise_text = concise(fact_order)
    style = rng.choices(list(STYLE_WEIGHTS), weights=list(STYLE_WEIGHTS.values()))[0]
    if style == "concise":
        reference = concise_text
    elif style == "verbose":
        extra = rng.sample(chosen_fillers, min(len(chosen_fillers), rng.choice([1, 2])))
        reference = " ".join([concise_text] + extra)
    else:  # terse: drop one non-subject key fact
        dropped = rng.choice(fact_order)
        reference = concise([f for f in fact_order if f != dropped])

    doc_words = set(_words(document))
    lc = len(_words(concise_text))
    meta = {
        "task": TASK_NAME,
        "kind": kind,
        "subject": list(subject),
        "facts": [{"name": f, "keys": [w for key in keys[f] for w in _words(key)]}
                  for f in [subject_fact] + fact_order],
        "entities": sorted({e for e in entities if e.lower() in doc_words}),
        "doc_words": sorted(doc_words),
        "band": [lc - BAND_BELOW, lc + BAND_ABOVE],
        "concise_summary": concise_text,
        "concise_length": lc,
        "style": style,
    }
    return {"prompt": PROMPT_TEMPLATE.format(document=document), "completion": " " + reference, "meta": meta}


def make_examples(n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
    """`n` examples {"prompt", "completion", "meta"}; deterministic in (n, seed, split)."""
    if split not in ("train", "eval"):
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = random.Random(f"{TASK_NAME}:{split}:{seed}")
    return [(_animal if rng.random() < 0.5 else _news)(rng, split) for _ in range(n)]


def corpus(n: int, seed: int) -> list[str]:
    """Texts for training the tokenizer: `n` train documents with their summaries (prompt +
    completion, so the cue words are included), plus one line holding every word of the
    task's vocabulary so eval-only combinations never meet an unseen word."""
    texts = [ex["prompt"] + ex["completion"] for ex in make_examples(n, seed, "train")]
    vocab_line = " ".join(
        NAMES + COLOURS + list(SPECIES_YOUNG) + sorted(set(SPECIES_YOUNG.values())) + REGIONS + HABITATS
        + FOODS + NUMBERS + CROWDS + DAYS + TOWNS + ACTORS + VERBS + list(OBJECT_UNITS)
        + list(OBJECT_UNITS.values()) + sorted(GLUE)
    )
    return texts + [vocab_line]


# --- gold scoring -------------------------------------------------------------------------

def _is_degenerate(words: list[str]) -> bool:
    if any(words[i] == words[i + 1] == words[i + 2] for i in range(len(words) - 2)):
        return True
    grams = [tuple(words[i:i + REPEAT_NGRAM]) for i in range(len(words) - REPEAT_NGRAM + 1)]
    return len(grams) != len(set(grams))


def _distance(meta: dict[str, Any], n_words: int) -> int:
    lo, hi = meta["band"]
    return max(0, lo - n_words, n_words - hi)


def _score(meta: dict[str, Any], summary: str) -> tuple[Fraction, dict[str, Any]]:
    text = summary.strip()
    words = _words(text)
    facts = meta["facts"]
    word_set = set(words)
    covered = [f["name"] for f in facts if all(k in word_set for k in f["keys"])]
    doc_words = set(meta["doc_words"])
    invented = sorted({w for w in words if w not in doc_words and w not in GLUE})
    degenerate = _is_degenerate(words)
    ends_with_period = text.endswith(".")
    capitalised = bool(text) and text[0].isupper()
    coverage = Fraction(len(covered), len(facts))
    faithfulness = max(Fraction(0), 1 - INVENTED_PENALTY * len(invented))
    repetition = DEGENERATE_FACTOR if degenerate else Fraction(1)
    if not words:
        quality = Fraction(0)
    else:
        quality = faithfulness * repetition * (
            W_COVERAGE * coverage + W_PERIOD * ends_with_period + W_CAPITAL * capitalised)
    distance = _distance(meta, len(words))
    breakdown = {
        "quality": float(quality),
        "coverage": float(coverage),
        "covered": covered,
        "missing": [f["name"] for f in facts if f["name"] not in covered],
        "invented": invented,
        "faithfulness": float(faithfulness),
        "ends_with_period": ends_with_period,
        "capitalised": capitalised,
        "degenerate": degenerate,
        "empty": not words,
        "length": len(words),
        "band": list(meta["band"]),
        "distance": distance,
        "in_band": distance == 0,
    }
    return quality, breakdown


def gold_breakdown(meta: dict[str, Any], summary: str) -> dict[str, Any]:
    """Every term of the gold quality plus length/band facts, JSON-serialisable."""
    return _score(meta, summary)[1]


def gold_quality(meta: dict[str, Any], summary: str) -> float:
    """Gold quality in [0, 1] (rules in the module docstring)."""
    return float(_score(meta, summary)[0])


def gold_key(meta: dict[str, Any], summary: str) -> tuple[int, float]:
    """(-distance from the length band, quality rounded to QUALITY_DECIMALS); larger is better."""
    quality, breakdown = _score(meta, summary)
    return (-breakdown["distance"], float(round(quality, QUALITY_DECIMALS)))


def gold_prefer(meta: dict[str, Any], a: str, b: str) -> int:
    """+1 if `a` is preferred, -1 if `b` is, 0 for a tie: length first, then quality."""
    ka, kb = gold_key(meta, a), gold_key(meta, b)
    return (ka > kb) - (ka < kb)


def win_rate(metas: Sequence[dict[str, Any]], candidates: Sequence[str], baselines: Sequence[str]) -> float:
    """Fraction of examples where the candidate beats the baseline; a tie counts half."""
    if not (len(metas) == len(candidates) == len(baselines)):
        raise ValueError(f"win_rate needs equal lengths, got {len(metas)} metas, "
                         f"{len(candidates)} candidates, {len(baselines)} baselines")
    if not metas:
        raise ValueError("win_rate of zero examples is undefined")
    wins = sum((gold_prefer(m, c, b) + 1) / 2 for m, c, b in zip(metas, candidates, baselines))
    return wins / len(metas)


def evaluate(metas: Sequence[dict[str, Any]], summaries: Sequence[str]) -> dict[str, float]:
    """Means over examples of the gold terms: quality, coverage, length, band hits, failures."""
    if len(metas) != len(summaries):
        raise ValueError(f"evaluate needs equal lengths, got {len(metas)} metas and {len(summaries)} summaries")
    if not metas:
        raise ValueError("evaluate of zero examples is undefined")
    rows = [gold_breakdown(m, s) for m, s in zip(metas, summaries)]
    n = len(rows)

    def mean(f) -> float:
        return sum(f(r) for r in rows) / n

    return {
        "n": n,
        "mean_quality": mean(lambda r: r["quality"]),
        "mean_coverage": mean(lambda r: r["coverage"]),
        "mean_length": mean(lambda r: r["length"]),
        "mean_distance": mean(lambda r: r["distance"]),
        "frac_in_band": mean(lambda r: r["in_band"]),
        "frac_too_long": mean(lambda r: r["length"] > r["band"][1]),
        "frac_too_short": mean(lambda r: r["length"] < r["band"][0]),
        "frac_empty": mean(lambda r: r["empty"]),
        "frac_degenerate": mean(lambda r: r["degenerate"]),
        "frac_invented": mean(lambda r: bool(r["invented"])),
        "frac_complete": mean(lambda r: r["coverage"] == 1.0),
    }
