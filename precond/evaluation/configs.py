"""Inference configurations as short names, so a grid is a list of strings on the command line and in caches.

`<generators>/<ranking>[/key=value...]`, generators joined by `+`:

    enumerate/subsumption            model+enumerate/recency/spp=4/dpp=2      model/recency/demos=4

keys: `guard` = `options.guarded` (`guard=spec`: its default from the spec; a config without `guard` guards
every action, the criterion before guarded actions existed), `lib` = the rule library (`lib=0`: none;
`lib=lodo`: built from the other development domains' `lib=0` inferences, precond/evaluation/library.py; a
config without `lib` has none, so that cached rows keep their meaning), `mnt` max new tokens per sample, `for` =
the request's `options.model_for` (`thin`: the model proposes
only for actions demonstrated fewer than 3 times), `spp` samples per prompt, `ppa` prompts per action, `dpp`
demonstrations per prompt, `seed`, `judge=1`, `rules=0` (the model asked about a thin action without
the rules the evidence settled for the others: the paper's prompt)
(the code model settles what the evidence leaves open, precond/engine/judging/judge.py), and
`demos` = how many of the domain's demonstrations the request gets (the first N; default all), and
`maxrate` = re-rank the same inference's valid candidates with precond/evaluation/ranking_probe.py (a measurement of
a ranking change, not an engine option), `tol` = the request's `options.tolerance` (0: the paper's strict
validation), `slips` = its `options.answer_slips` (0: a notice keeps "an answer came"), and for the noise and
sparsity sweep (precond/evaluation/noise.py, SGD only): `sample` = draw the
`demos` demonstrations at random with this seed (instead of the first N), `noise` = inject agent errors at
this share of the system steps (seeded by `sample`).
Two names are baselines that run no inference: `always` (no precondition: every action always allowed)
and `gt` (the ground truth; must score 1.0, a check of the scoring pipeline).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, get_args

from precond_client.schemas import DEFAULT_TOLERANCE, Generator, InferOptions, Ranking

BASELINES = ("always", "gt")
_SUCCESS = {"SUCCESS": ("self.query_success",), "CONFIRMED": ("self.query_success",)}
_EMPTY = ("not self.query_success",)
_ASKED = ("self.query_success is False",)
NOTICE_READINGS: dict[str, dict[str, tuple[str, ...]]] = {
    "off": {},
    "empty": {"FAIL": _EMPTY, "NOTHING_FOUND": _EMPTY, **_SUCCESS},
    "found-asked": {"FAIL": _EMPTY, "NOTHING_FOUND": _ASKED, **_SUCCESS},
    "asked": {"FAIL": _ASKED, "NOTHING_FOUND": _ASKED, **_SUCCESS},
    "found-asked-available": {"FAIL": _EMPTY, "NOTHING_FOUND": _ASKED, "NOT_AVAILABLE": _ASKED, **_SUCCESS},
    "empty-available": {"FAIL": _EMPTY, "NOTHING_FOUND": _EMPTY, "NOT_AVAILABLE": _EMPTY, **_SUCCESS},
}
"""`notices=<reading>`: the signed notices a `lib=lodo` config's library carries
(precond/engine/candidates/library.py `SIGNED`): what a failure notice, "nothing found" and "not available" need
of the last result. `empty`: an answer that is no success (also before anything was asked); `asked`: an answer
came and it was no success."""
_KEYS = {"spp": "samples_per_prompt", "ppa": "prompts_per_action", "dpp": "demonstrations_per_prompt",
         "seed": "seed", "judge": "judge", "mnt": "max_new_tokens",
         "rules": "show_rules"}
DEMO_COUNTS = (1, 2, 4)

GRIDS: dict[str, tuple[str, ...]] = {
    "baselines": BASELINES,
    "enumerate": ("enumerate/subsumption", "enumerate/recency", "enumerate/marginal"),
    "enumerate-demos": tuple(f"enumerate/{r}/demos={n}"
                             for r in ("subsumption", "recency") for n in DEMO_COUNTS),
    "model": ("model/subsumption", "model/recency", "model+enumerate/subsumption", "model+enumerate/recency",
              "model+enumerate/recency/for=all", "enumerate/recency/judge=1"),
    "probe": ("enumerate/recency/maxrate=0.9", "enumerate/subsumption/maxrate=0.9",
              "model+enumerate/recency/maxrate=0.9"),
    "model-ablation": ("model/recency/spp=2", "model/recency/spp=16", "model/recency/dpp=2",
                       "model/recency/demos=2"),
}
SWEEP_TOLERANCES = (0.0, DEFAULT_TOLERANCE)
SWEEP_SEEDS = (0, 1, 2)
SWEEP_DEMOS = (1, 2, 3, 5)
SWEEP_NOISE = (0.02, 0.05, 0.1)


def sweep(base: str = "enumerate/recency") -> tuple[str, ...]:
    """Strict and tolerant validation on fewer demonstrations (clean) and on all ten with injected errors."""
    names = []
    for tol in SWEEP_TOLERANCES:
        names.append(f"{base}/tol={tol:g}")
        names += [f"{base}/tol={tol:g}/demos={n}/sample={s}" for n in SWEEP_DEMOS for s in SWEEP_SEEDS]
        names += [f"{base}/tol={tol:g}/noise={r:g}/sample={s}" for r in SWEEP_NOISE for s in SWEEP_SEEDS]
    return tuple(names)


GRIDS["noise"] = sweep()
GRIDS["no-model"] = GRIDS["baselines"] + GRIDS["enumerate"] + GRIDS["enumerate-demos"]
GRIDS["default"] = GRIDS["no-model"] + GRIDS["model"]


@dataclass(frozen=True)
class InferConfig:
    name: str
    baseline: str | None = None
    generators: tuple[str, ...] = ()
    ranking: str = "subsumption"
    demos: int | None = None
    options: dict[str, Any] = field(default_factory=dict)
    max_rate: float | None = None
    sample: int | None = None
    noise: float = 0.0
    notices: str | None = None

    @property
    def base(self) -> InferConfig:
        """The engine inference a probe re-ranks: the same name without its `maxrate=` part."""
        name = "/".join(p for p in self.name.split("/") if not p.startswith("maxrate="))
        return parse_config(name)

    @property
    def uses_model(self) -> bool:
        return "model" in self.generators or bool(self.options.get("judge"))

    @property
    def library(self) -> bool:
        return bool(self.options.get("library"))

    def infer_options(self, actions: Sequence[str] = ()) -> InferOptions:
        """`guard=spec` is the request's default (`options.guarded` null); without `guard`, every action is guarded
        (the criterion before guarded actions existed), so cached rows keep their meaning."""
        options: dict[str, Any] = {"library": False, "candidates": "all", **self.options}  # probes rerank all valid
        guard = options.pop("guarded", "all")
        if guard == "all":
            options["guarded"] = list(actions)
        return InferOptions(generators=list(self.generators), ranking=self.ranking, **options)  # type: ignore[arg-type]


def parse_config(name: str) -> InferConfig:
    if name in BASELINES:
        return InferConfig(name, baseline=name)
    parts = name.split("/")
    if len(parts) < 2:
        raise ValueError(f"config {name!r}: expected <generators>/<ranking>[/key=value...] or {BASELINES}")
    generators = tuple(parts[0].split("+"))
    for g in generators:
        if g not in get_args(Generator):
            raise ValueError(f"config {name!r}: unknown generator {g!r}")
    if parts[1] not in get_args(Ranking):
        raise ValueError(f"config {name!r}: unknown ranking {parts[1]!r}")
    options: dict[str, Any] = {}
    demos: int | None = None
    max_rate: float | None = None
    sample: int | None = None
    noise = 0.0
    notices: str | None = None
    for item in parts[2:]:
        key, _, value = item.partition("=")
        if key == "maxrate":
            max_rate = float(value)
        elif key == "tol":
            options["tolerance"] = float(value)
        elif key == "slips":
            options["answer_slips"] = float(value)
        elif key == "sample":
            sample = int(value)
        elif key == "noise":
            noise = float(value)
        elif key == "for":
            options["model_for"] = value
        elif key == "unseen":
            options["unseen"] = value
        elif key == "guard":
            if value not in ("all", "spec"):
                raise ValueError(f"config {name!r}: guard={value!r}: expected all or spec")
            options["guarded"] = value
        elif key == "notices":
            if value not in NOTICE_READINGS:
                raise ValueError(f"config {name!r}: notices={value!r}: expected one of {sorted(NOTICE_READINGS)}")
            notices = value
        elif key == "lib":
            if value not in ("0", "lodo"):
                raise ValueError(f"config {name!r}: lib={value!r}: expected 0 (no rule library) or lodo")
            options["library"] = value == "lodo"
        elif key == "demos":
            demos = None if value == "all" else int(value)
        elif key in _KEYS:
            options[_KEYS[key]] = int(value)
        else:
            known = ", ".join(["demos", "maxrate", "tol", "sample", "noise", "for", "unseen", "lib", "guard",
                               "notices", *_KEYS])
            raise ValueError(f"config {name!r}: unknown key {key!r} (known: {known})")
    config = InferConfig(name, None, generators, parts[1], demos, options, max_rate, sample, noise, notices)
    config.infer_options()  # fail now on out-of-range values, not after an hour of other configs
    return config


def expand(names: str) -> list[InferConfig]:
    """Comma-separated config names and grid names (`default`, `no-model`, `model`, ...), deduplicated."""
    out: list[str] = []
    for item in (n.strip() for n in names.split(",") if n.strip()):
        out.extend(GRIDS.get(item, (item,)))
    return [parse_config(n) for n in dict.fromkeys(out)]
