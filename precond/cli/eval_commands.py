"""`precond eval preconditions|policy|report|all`: the evaluation harness (precond/evaluation/, docs/results.md).

Everything expensive is cached under `--cache` (default `.eval-cache/`, gitignored), so every command can be
interrupted and re-run, and `precond eval all` regenerates docs/results.md from whatever is cached plus the
cheap model-free configurations.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Annotated, Any

import typer

from precond.evaluation.cache import DEFAULT_CACHE, JsonCache

DataOption = Annotated[
    list[Path] | None,
    typer.Option("--data", help="Data directories (default: sgd/, star/ and alfworld/ of PRECOND_DATA_DIR, else "
                 "../shared/data); repeatable."),
]
CacheOption = Annotated[Path, typer.Option("--cache", help="Directory of cached runs.")]
VariantsOption = Annotated[int, typer.Option(min=1, max=32, help="Changed copies of each test trajectory.")]
SeedOption = Annotated[int, typer.Option(min=0, help="Seed of the changes.")]
REPORT = Path("docs/results.md")
BENCHMARK_DIRS = ("sgd", "star", "alfworld")


@cache
def _engine(with_model: bool) -> Any:
    """One engine per process; the model loads on its first use only."""
    import torch

    from precond.engine.factory import build_engine

    torch.set_num_threads(1)
    return build_engine(with_model=with_model)


def _sandbox() -> Any:
    """Scoring runs every test trajectory of a domain in one call: more time than a request is allowed."""
    from precond.engine.settings import SandboxSettings

    return SandboxSettings().build_for_scoring()


def _data(data: list[Path] | None, *names: str) -> list[Path]:
    """The given directories, or the named ones under the data directory; a missing one stops the command
    with a message naming the path and the setting (PRECOND_DATA_DIR)."""
    from precond.evaluation.settings import DataMissing, DataSettings, missing_message

    try:
        if not data:
            return [DataSettings().path(name) for name in names]
        for path in data:
            if not path.exists():
                raise DataMissing(missing_message(path))
    except DataMissing as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    return data


def _domains(data: list[Path] | None, alfworld_modes: str) -> list[Any]:
    """Every domain of the directories, or exit 2 naming the one that is missing or malformed: a table of the
    domains that could be read is never presented as the whole."""
    from precond.evaluation.domains import ARG_MODES, DomainDataError, load_domains

    data = _data(data, *BENCHMARK_DIRS)
    modes = [m.strip() for m in alfworld_modes.split(",") if m.strip()]
    out = []
    try:
        for path in data:
            if (path / "demos.json").exists():
                for mode in modes:
                    if mode not in ARG_MODES:
                        raise typer.BadParameter(f"unknown ALFWorld argument mode {mode!r}; known: {ARG_MODES}")
                    out.extend(load_domains(path, mode))
            else:
                out.extend(load_domains(path))
    except DomainDataError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    return out


def preconditions(
    data: DataOption = None,
    configs: Annotated[str, typer.Option(help="Config names or grids (see precond/evaluation/configs.py)")]
    = "no-model",
    alfworld_args: Annotated[str, typer.Option(help="ALFWorld argument domains: state, trajectory or both.")]
    = "state,trajectory",
    cache_dir: CacheOption = DEFAULT_CACHE,
    force: Annotated[bool, typer.Option(help="Re-run inference even when cached.")] = False,
) -> None:
    """Infer preconditions per domain and configuration; score P/R/F1 on the test trajectories."""
    from precond.evaluation.configs import expand
    from precond.evaluation.preconditions import evaluate
    from precond.evaluation.report import precondition_table, store_precondition_results

    store = JsonCache(cache_dir)
    chosen = expand(configs)
    needs_model = any(c.uses_model for c in chosen)
    from precond.evaluation.scoring import Satisfaction

    domains = _domains(data, alfworld_args)
    sandbox = _sandbox()
    result = evaluate(domains, chosen, store, Satisfaction(sandbox, store),
                      lambda: _engine(needs_model).infer, force, sandbox)
    path = store_precondition_results(store, result)
    typer.echo(precondition_table(result["summary"]))
    typer.echo(f"\nper-domain and per-action results: {path}")


def policy(
    data: Annotated[Path | None, typer.Option("--data", help="The SGD data directory (default: sgd/ of the "
                                                 "data directory, PRECOND_DATA_DIR).")] = None,
    configs: Annotated[str, typer.Option(help="Policy configs or grids (precond/evaluation/policy.py).")] = "default",
    domains: Annotated[str, typer.Option(help="SGD services, comma-separated; empty: all.")] = "",
    dialogs: Annotated[int, typer.Option(help="First N test dialogs per domain.")] = 2,
    turns: Annotated[int, typer.Option(help="First N system turns per dialog.")] = 6,
    inferred_from: Annotated[str, typer.Option(help="Precondition config for the 'inferred' rows.")]
    = "model+enumerate/recency",
    cache_dir: CacheOption = DEFAULT_CACHE,
) -> None:
    """Next-action prediction at system turns: turn F1 and GT precondition compatibility."""
    from precond.evaluation.configs import parse_config
    from precond.evaluation.policy import expand_policy, run_policy, summarize_policy
    from precond.evaluation.preconditions import infer
    from precond.evaluation.report import policy_table, store_policy_results

    (data,) = _data([data] if data else None, "sgd")
    store = JsonCache(cache_dir)
    wanted = {d.strip() for d in domains.split(",") if d.strip()}
    chosen = [d for d in _domains([data], "state") if not wanted or d.name in wanted]
    source = parse_config(inferred_from)
    engine = _engine(True)
    rows = []
    for domain in chosen:
        raw = json.loads(next(p for p in data.glob("*.json") if p.stem == domain.name).read_text())
        inferred = infer(domain, source, store, lambda: engine.infer)
        for config in expand_policy(configs):
            pre = domain.gt if config.source == "gt" else inferred.preconditions
            results = run_policy(engine, domain, config, pre, raw["test"][:dialogs], store, turns)
            rows.append({"domain": domain.name, "config": config.name, "inferred_from": source.name,
                         "dialogs": dialogs, "max_turns": turns} | summarize_policy(results))
    path = store_policy_results(store, rows)
    typer.echo(policy_table(rows))
    typer.echo(f"\nresults: {path}")


def next_action(
    data: Annotated[Path | None, typer.Option("--data", help="The SGD data directory (default: sgd/ of the "
                                                 "data directory, PRECOND_DATA_DIR).")] = None,
    configs: Annotated[str, typer.Option(help="Policy configs or grids (precond/evaluation/policy.py).")] = "modes",
    turns: Annotated[int, typer.Option(help="System turns per domain, at least (whole dialogs, seeded).")] = 100,
    seed: Annotated[int, typer.Option(help="Seed of the dialog sample (and of the model's sampling).")] = 0,
    baseline: Annotated[str, typer.Option(help="The config paired differences are taken against.")]
    = "none/plain/shots=1",
    inferred_from: Annotated[str, typer.Option(help="Precondition config for the 'inferred' rows (model-free "
                                               "by default: cheap, and within 0.002 F1 of the model's).")]
    = "enumerate/recency",
    cached_only: Annotated[bool, typer.Option(help="Predict nothing: summarize the dialogs every config has "
                                              "finished (what an interrupted run has so far).")] = False,
    cache_dir: CacheOption = DEFAULT_CACHE,
) -> None:
    """Next action at size: all SGD domains, a seeded sample of turns, intervals and paired differences."""
    from precond.evaluation.configs import parse_config
    from precond.evaluation.policy import expand_policy
    from precond.evaluation.preconditions import infer
    from precond.evaluation.report import store_sized_results, write_next_action_section
    from precond.evaluation.sized import Task, finished, run, sample_dialogs, summarize

    (data,) = _data([data] if data else None, "sgd")
    store = JsonCache(cache_dir)
    engine, memo = _memo_engine(store)
    policies = _PolicyEngines(engine, memo, store, cache_dir)
    source = parse_config(inferred_from)
    tasks = []
    for domain in _domains([data], "state"):
        raw = json.loads(next(p for p in data.glob("*.json") if p.stem == domain.name).read_text())
        inferred = infer(domain, source, store, lambda: engine.infer)
        tasks.append(Task(domain, sample_dialogs(raw["test"], turns, seed), inferred.preconditions))
    results = run(policies.engine_for, tasks, expand_policy(configs), store, seed, policies.replayed, cached_only)
    rows = summarize(results, baseline)
    path = store_sized_results(store, {"rows": rows, "inferred_from": source.name, "turns_per_domain": turns,
                                       "seed": seed, "training": policies.training, "complete": not cached_only or all(
                                           finished(store, t, d, expand_policy(configs))
                                           for t in tasks for d in t.dialogs)})
    write_next_action_section(store, REPORT)
    typer.echo(json.dumps(rows, indent=1))
    typer.echo(f"\nresults: {path}; section written into {REPORT}")


def next_action_alfworld(
    data: Annotated[Path | None, typer.Option("--data", help="The ALFWorld data directory (default: alfworld/ "
                                                 "of the data directory, PRECOND_DATA_DIR).")] = None,
    configs: Annotated[str, typer.Option(help="Policy configs or grids (precond/evaluation/policy.py).")]
    = "none/plain/shots=1,inferred/constrained/shots=1",
    episodes: Annotated[int, typer.Option(help="valid_unseen trajectories (seeded order).")] = 10,
    steps: Annotated[int, typer.Option(help="Action steps per trajectory, spread evenly.")] = 3,
    seed: Annotated[int, typer.Option(help="Seed of the sample (and of the model's sampling).")] = 0,
    baseline: Annotated[str, typer.Option(help="The config paired differences are taken against.")]
    = "none/plain/shots=1",
    inferred_from: Annotated[str, typer.Option(help="Precondition config for the 'inferred' rows.")]
    = "enumerate/recency",
    cache_dir: CacheOption = DEFAULT_CACHE,
) -> None:
    """Next action in ALFWorld: share of predictions the simulator admits, and match with the expert."""
    from precond.evaluation.alfworld_next import run, sample_episodes, summarize
    from precond.evaluation.configs import parse_config
    from precond.evaluation.domains import ALFWORLD_TEST_SPLIT
    from precond.evaluation.policy import expand_policy
    from precond.evaluation.preconditions import infer
    from precond.evaluation.report import write_next_action_section

    (data,) = _data([data] if data else None, "alfworld")
    store = JsonCache(cache_dir)
    engine, memo = _memo_engine(store)
    policies = _PolicyEngines(engine, memo, store, cache_dir)
    domain = _domains([data], "state")[0]
    if domain.benchmark != "alfworld":
        typer.echo(f"error: domain directory {data}: not the ALFWorld directory (no demos.json)", err=True)
        raise typer.Exit(2)
    inferred = infer(domain, parse_config(inferred_from), store, lambda: engine.infer).preconditions
    trajectories = [t for t in json.loads((data / "test.json").read_text())["trajectories"]
                    if t["split"] == ALFWORLD_TEST_SPLIT and not t.get("same_scene_as_demo")]
    demos = json.loads((data / "demos.json").read_text())["trajectories"]
    admissible = json.loads((data / "test_admissible_commands.json").read_text())["admissible_commands"]
    sample = sample_episodes(trajectories, demos, admissible, episodes, steps, seed)
    results = run(lambda config: policies.for_domain(domain, config), domain.spec, sample, expand_policy(configs),
                  lambda c: dict(domain.gt) if c.source == "gt" else inferred, store, seed, policies.replayed)
    rows = summarize(results, baseline)
    path = store.put({"rows": rows, "inferred_from": inferred_from, "episodes": episodes, "steps": steps,
                      "seed": seed, "training": policies.training}, "results", "next-action-alfworld")
    write_next_action_section(store, REPORT)
    typer.echo(json.dumps(rows, indent=1))
    typer.echo(f"\nresults: {path}; section written into {REPORT}")


def tools(
    data: Annotated[Path | None, typer.Option("--data", help="The tau-bench airline directory (default: "
                                                 "tau-airline/ of the data directory, PRECOND_DATA_DIR).")] = None,
    configs: Annotated[str, typer.Option(help="ranking/tolerance pairs, comma-separated (e.g. marginal/0); "
                                         "empty: the grid of precond/evaluation/tools.py.")] = "",
    cache_dir: CacheOption = DEFAULT_CACHE,
    labels: Annotated[bool, typer.Option("--labels", help="Score on labels.json instead, trained on half the tasks "
                                         "and judged on the other half, both ways, with and without the labels "
                                         "as counterexamples; per direction, tool, policy rule and what each "
                                         "refusal rests on (precond/evaluation/tools_labels.py).")] = False,
    domain: Annotated[Path | None, typer.Option("--domain", help="Score a domain you wrote instead: tools.json, "
                                                "trajectories.json, labels and a test set (test.json, "
                                                "test_verdicts.json; precond/evaluation/tools_domain.py).",
                                                show_default=False)] = None,
) -> None:
    """Guard tool calls: rules from the successful airline runs, judged on every state-changing call."""
    from precond.evaluation.tools import CONFIGS, GuardConfig, run
    from precond.evaluation.tools_report import write_tools_section

    if domain is not None:
        _score_domain(domain, cache_dir)
        return
    (data,) = _data([data] if data else None, "tau-airline")
    if labels:
        from precond.evaluation import tools_labels

        if not (data / "labels.json").is_file():
            typer.echo(f"error: {data / 'labels.json'}: no labels there", err=True)
            raise typer.Exit(2)
        scored = tools_labels.run(_engine(False), data, typer.echo)
        path = JsonCache(cache_dir).put(scored, "results", "tools-labels")
        typer.echo(tools_labels.table(scored) + f"\nresults: {path}")
        return
    chosen = list(CONFIGS)
    if configs.strip():
        try:
            chosen = [GuardConfig(r, None if t == "default" else float(t))
                      for r, _, t in (c.strip().partition("/") for c in configs.split(",") if c.strip())]
        except ValueError as exc:
            raise typer.BadParameter(f"--configs: {exc} (expected ranking/tolerance, e.g. marginal/0)") from None
    store = JsonCache(cache_dir)
    result = run(_engine(False), data, chosen, typer.echo)
    path = store.put(result, "results", "tools")
    write_tools_section(store, REPORT)
    typer.echo(f"chosen: {result['chosen']}; results: {path}; section written into {REPORT}")


def _score_domain(domain: Path, cache_dir: Path) -> None:
    from precond.evaluation import tools_domain

    missing = [n for n in ("tools.json", "trajectories.json", "test.json", "test_verdicts.json")
               if not (domain / n).is_file()]
    if missing:
        typer.echo(f"error: {domain / missing[0]}: no such file (a domain has tools.json, trajectories.json, "
                   "test.json and test_verdicts.json)", err=True)
        raise typer.Exit(2)
    scored = tools_domain.run(_engine(False), domain, typer.echo)
    path = JsonCache(cache_dir).put(scored, "results", f"tools-domain-{domain.resolve().name}")
    typer.echo(tools_domain.table(scored) + f"\nresults: {path}")


class _PolicyEngines:
    """The engine of each row: the base model's for Act, a domain's fine-tuned model for BC (trained on first
    use, precond/evaluation/bc.py); one clock over all their memos."""

    def __init__(self, base: Any, memo: Callable[[], float], store: JsonCache, root: Path) -> None:
        self.base, self.memo, self.store, self.root = base, memo, store, root
        self.built: dict[str, tuple[Any, Callable[[], float]]] = {}
        self.training: dict[str, dict[str, Any]] = {}

    def engine_for(self, task: Any, config: Any) -> Any:
        return self.for_domain(task.domain, config)

    def for_domain(self, domain: Any, config: Any) -> Any:
        if config.policy != "bc":
            return self.base
        name = domain.name
        if name not in self.built:
            from precond.evaluation.bc import trained

            adapter, result = trained(self.root, domain)
            self.training[name] = {"seconds": result.seconds, "steps": result.steps, "examples": result.examples,
                                   "action_lines": result.action_lines, "final_loss": result.losses[-1],
                                   "adapter_bytes": result.adapter_bytes, "adapter": adapter.name}
            self.built[name] = _memo_engine(self.store, adapter)
        return self.built[name][0]

    def replayed(self) -> float:
        return self.memo() + sum(clock() for _, clock in self.built.values())


def _memo_engine(store: JsonCache, adapter: Path | None = None) -> tuple[Any, Callable[[], float]]:
    """An engine whose model remembers completions in the cache (precond/evaluation/memo.py), and the memo's clock."""
    import torch

    from precond.engine.factory import build_engine
    from precond.evaluation.memo import MemoModel

    torch.set_num_threads(1)
    memo: list[MemoModel] = []

    def remembering(model: Any) -> Any:
        memo.append(MemoModel(model, store))
        return memo[0]

    def replayed() -> float:
        return memo[0].take_replayed() if memo else 0.0

    return build_engine(wrap_model=remembering, adapter=adapter), replayed


def report(
    cache_dir: CacheOption = DEFAULT_CACHE,
    out: Annotated[Path, typer.Option(help="Markdown file to write; plots go to img/ beside it.")]
    = Path("docs/results.md"),
    bench: Annotated[Path, typer.Option(help="Sandbox benchmark script (run with --json if present).")]
    = Path("bench/sandbox_bench.py"),
    noise_only: Annotated[bool, typer.Option(help="Rewrite only the noise and sparsity section of OUT (from "
                                             "`--configs noise`), keeping the rest as it is.")] = False,
    next_action_only: Annotated[bool, typer.Option(help="Only (re)write the next-action section and its plot, "
                                                   "keeping the rest of the report as it is.")] = False,
) -> None:
    """Regenerate docs/results.md and docs/img/*.png from the cached results."""
    from precond.evaluation.report import write_next_action_section, write_noise_section, write_report

    if noise_only:
        write_noise_section(JsonCache(cache_dir), out)
    elif next_action_only:
        write_next_action_section(JsonCache(cache_dir), out)
    else:
        write_report(JsonCache(cache_dir), out, bench)
    typer.echo(f"wrote {out}")


def run_all(
    data: DataOption = None,
    cache_dir: CacheOption = DEFAULT_CACHE,
    configs: Annotated[str, typer.Option(help="Precondition configs to (re)score.")] = "no-model,probe",
) -> None:
    """Re-score every config from the cache (model configs only if cached: no model is loaded), then report."""
    from precond.evaluation.configs import expand
    from precond.evaluation.preconditions import evaluate
    from precond.evaluation.report import store_precondition_results
    from precond.evaluation.scoring import Satisfaction

    store = JsonCache(cache_dir)
    known = ",".join(r["config"] for r in (store.get("results", "preconditions") or {"rows": []})["rows"])
    domains = _domains(data, "state,trajectory")
    sandbox = _sandbox()
    result = evaluate(domains, expand(f"{configs},{known}"), store,
                      Satisfaction(sandbox, store), lambda: _engine(False).infer, False, sandbox)
    store_precondition_results(store, result)
    report(cache_dir=cache_dir, out=Path("docs/results.md"), bench=Path("bench/sandbox_bench.py"), noise_only=False)


def counterfactual(
    data: DataOption = None,
    configs: Annotated[str, typer.Option(help="Config names or grids (see precond/evaluation/configs.py).")]
    = "",
    variants: VariantsOption = 4,
    seed: SeedOption = 0,
    cache_dir: CacheOption = DEFAULT_CACHE,
    out: Annotated[Path, typer.Option(help="Report whose counterfactual section is (re)written.")] = REPORT,
) -> None:
    """The paper's F1 beside counterfactual safety (unsafe_allow, over_refuse) per config and domain."""
    from precond.evaluation.configs import expand
    from precond.evaluation.safety import DEFAULT_CONFIGS, evaluate, table, write_section
    from precond.evaluation.scoring import Satisfaction

    store = JsonCache(cache_dir)
    chosen = expand(configs or DEFAULT_CONFIGS)
    needs_model = any(c.uses_model for c in chosen)
    rows = evaluate(_domains(data, "state"), chosen, store, Satisfaction(_sandbox(), store),
                    lambda: _engine(needs_model).infer, variants, seed)
    store.put(rows, "results", "counterfactual")
    write_section(rows, out, chosen[0].name)
    typer.echo(table(rows))
    typer.echo(f"\nwrote the counterfactual section of {out}")
    _fail_on_errors(rows)


def _fail_on_errors(rows: list[dict[str, Any]]) -> None:
    """Exit 1 naming every (config, domain) whose inference failed: its table says "error" there, and a
    benchmark's mean over the rest says "incomplete", so a run that lost a domain never reads as whole."""
    failed = [f"{r['domain']} ({r['config']}): {r['error']}" for r in rows if r.get("error") is not None]
    if failed:
        typer.echo(f"error: {len(failed)} run(s) failed, the table above is incomplete:\n  " + "\n  ".join(failed),
                   err=True)
        raise typer.Exit(1)


def domains(
    data: DataOption = None,
    configs: Annotated[str, typer.Option(help="Config names or grids (see precond/evaluation/configs.py).")]
    = "",
    variants: VariantsOption = 4,
    seed: SeedOption = 0,
    cache_dir: CacheOption = DEFAULT_CACHE,
    out: Annotated[Path, typer.Option(help="Report whose twenty-domain section is (re)written.")] = REPORT,
    max_unsafe: Annotated[float | None, typer.Option(
        min=0.0, max=1.0, help="Fail (exit 1, naming each domain and its numbers) when a config's counterfactual "
                               "unsafe share on any domain exceeds this bound.")] = None,
    unsafe_against: Annotated[str | None, typer.Option(
        help="Fail (exit 1, naming each domain) when a config's unsafe share on any domain exceeds this config's "
             "beyond noise (precond/evaluation/choice.py); the config is measured too.")] = None,
    actions: Annotated[int, typer.Option(min=0, help="Also print, per benchmark, the N actions of the first config "
                                                     "(not a baseline) that over-refuse most and the N that let "
                                                     "most through, with their rules.")] = 0,
) -> None:
    """Every development domain (SGD, STAR, ALFWorld): per benchmark the mean, the worst domain and the domains at
    or below `always`, for the paper's F1 and the counterfactual metric (precond/evaluation/generalisation.py);
    with `--max-unsafe`, a config that breaks the bound on any domain fails the command."""
    from precond.evaluation.choice import raised_against
    from precond.evaluation.configs import expand
    from precond.evaluation.generalisation import (
        DEFAULT_CONFIGS,
        costly_actions,
        first_measured,
        summarize,
        summary_table,
        unsafe_breaches,
        write_section,
    )
    from precond.evaluation.safety import evaluate
    from precond.evaluation.scoring import Satisfaction

    store = JsonCache(cache_dir)
    chosen = expand(",".join([configs or DEFAULT_CONFIGS, "always", unsafe_against or ""]))  # `<=always` needs it
    engine = _memo_engine(store)[0]  # completions remembered: a config that asks the same question pays once
    rows = evaluate(_domains(data, "state"), chosen, store, Satisfaction(_sandbox(), store),
                    lambda: engine.infer, variants, seed)
    store.put(rows, "results", "domains")
    write_section(rows, out)
    typer.echo(summary_table(summarize(rows)))
    typer.echo(f"\nwrote the twenty-domain section of {out}")
    if actions and (first := first_measured(rows)) is not None:
        typer.echo(f"\nthe costliest actions of {first}:\n{costly_actions(rows, first, actions)}")
    breaches = unsafe_breaches(rows, max_unsafe) if max_unsafe is not None else []
    if breaches:
        typer.echo(f"error: {len(breaches)} domain(s) above --max-unsafe:\n  " + "\n  ".join(breaches), err=True)
    raised = raised_against(rows, unsafe_against) if unsafe_against else []
    if raised:
        typer.echo(f"error: {len(raised)} domain(s) less safe than {unsafe_against}:\n  " + "\n  ".join(raised),
                   err=True)
    if breaches or raised:
        raise typer.Exit(1)


def choose(
    data: DataOption = None,
    base: Annotated[str, typer.Option(help="The config each candidate changes (model-free: the model is not "
                                           "loaded).")] = "enumerate/cautious/guard=spec/lib=lodo",
    only: Annotated[str, typer.Option("--choices", help="Comma-separated choice names (default: all).")] = "",
    variants: VariantsOption = 4,
    seed: SeedOption = 0,
    cache_dir: CacheOption = DEFAULT_CACHE,
    out: Annotated[Path | None, typer.Option(help="Also write the tables to this Markdown file.")] = None,
) -> None:
    """Each data-driven choice of the learner (precond/evaluation/choice.py): its candidates on every development
    domain, picked by leave-one-domain-out on F1 among those that raise the counterfactual unsafe share on no
    domain beyond noise. Exit 1 naming the choice when a pick is not what ships, or when a run failed."""
    from precond.evaluation.choice import CHOICES, by_candidate, config_name, decide
    from precond.evaluation.configs import expand
    from precond.evaluation.safety import evaluate
    from precond.evaluation.scoring import Satisfaction

    wanted = [c.strip() for c in only.split(",") if c.strip()]
    unknown = [w for w in wanted if w not in {c.name for c in CHOICES}]
    if unknown:
        raise typer.BadParameter(f"unknown choice(s) {unknown}; known: {[c.name for c in CHOICES]}",
                                 param_hint="--choices")
    store = JsonCache(cache_dir)
    domains_ = _domains(data, "state")
    sat = Satisfaction(_sandbox(), store)
    texts, differ = [], []
    for choice in [c for c in CHOICES if not wanted or c.name in wanted]:
        configs = expand(",".join(config_name(base, s) for s in choice.candidates.values()))
        rows = evaluate(domains_, configs, store, sat, lambda: _engine(False).infer, variants, seed)
        _fail_on_errors(rows)
        outcome = decide(choice, by_candidate(choice, base, rows))
        texts.append(outcome.text)
        typer.echo(outcome.text)
        if outcome.picked != choice.shipped:
            differ.append(f"{choice.name}: picked {outcome.picked}, ships {choice.shipped}")
    if out is not None:
        out.write_text("\n".join(texts), encoding="utf-8")
    if differ:
        typer.echo("error: the shipped default is not the pick:\n  " + "\n  ".join(differ), err=True)
        raise typer.Exit(1)


def library(
    config: Annotated[str, typer.Option(help="The configuration whose rules (without a library) are shipped.")]
    = "model+enumerate/cautious",
    cache_dir: CacheOption = DEFAULT_CACHE,
) -> None:
    """Build the rule library shipped with the service (precond/engine/data/rule_library.json) from every
    development domain's inferred rules (never their ground truth)."""
    from precond.evaluation.configs import parse_config
    from precond.evaluation.library import build, development_domains, write_shipped
    from precond.evaluation.preconditions import infer

    _data(None, *BENCHMARK_DIRS)
    store = JsonCache(cache_dir)
    chosen = parse_config(config)
    built = build(development_domains(), chosen, store,
                  lambda d, c: infer(d, c, store, lambda: _engine(c.uses_model).infer))
    path = write_shipped(built)
    typer.echo(f"wrote {path}: {len(built.sources)} sources ({', '.join(s.source for s in built.sources)})")


def transfer(
    config: Annotated[str, typer.Option(help="The configuration inferred with and without priors.")]
    = "model+enumerate/cautious",
    force: Annotated[bool, typer.Option(help="Infer again (for timings) instead of reading the cache.")] = False,
    out: Annotated[Path, typer.Option(help="Report whose transfer section is (re)written.")] = REPORT,
    data: DataOption = None, cache_dir: CacheOption = DEFAULT_CACHE, variants: VariantsOption = 4,
    seed: SeedOption = 0,
) -> None:
    """Prior rules, leave one SGD domain out: F1 and counterfactual safety with and without the other domains'
    inferred rules, and the ALFWorld control (precond/evaluation/transfer.py)."""
    from precond.evaluation.configs import parse_config
    from precond.evaluation.scoring import Satisfaction
    from precond.evaluation.transfer import evaluate, table, write_section

    store = JsonCache(cache_dir)
    chosen = parse_config(config)
    domains = _domains(data, "state")
    sgd = [d for d in domains if d.benchmark == "sgd"]
    alfworld = next((d for d in domains if d.benchmark == "alfworld"), None)
    rows = evaluate(sgd, alfworld, chosen, store, Satisfaction(_sandbox(), store),
                    lambda: _engine(chosen.uses_model).infer, variants, seed, force)
    store.put(rows, "results", "transfer")
    write_section(rows, out)
    typer.echo(table(rows))
    typer.echo(f"\nwrote the transfer section of {out}")


def register(app: typer.Typer) -> None:
    group = typer.Typer(help="Evaluate precondition inference and the policy on the development data.",
                        no_args_is_help=True)
    group.command("preconditions")(preconditions)
    group.command("policy")(policy)
    group.command("next-action")(next_action)
    group.command("next-action-alfworld")(next_action_alfworld)
    group.command("counterfactual")(counterfactual)
    group.command("transfer")(transfer)
    group.command("domains")(domains)
    group.command("choose")(choose)
    group.command("library")(library)
    group.command("tools")(tools)
    group.command("report")(report)
    group.command("all")(run_all)
    app.add_typer(group, name="eval")
