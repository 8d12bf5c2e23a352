"""``make bench`` can regenerate every results file: each names a command that exists."""

import importlib.util
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]

_spec = importlib.util.spec_from_file_location('run_all', REPO_ROOT / 'bench' / 'run_all.py')
run_all = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(run_all)


def test_every_results_file_has_a_command_that_exists():
    """No results file without a runnable Reproduce command; every script and flag exists."""
    benchmarks, orphans = run_all.registry()
    assert not orphans, f'results files with no command: {orphans}'
    names = {p.stem for p in (REPO_ROOT / 'bench' / 'results').glob('*.md')}
    assert set(benchmarks) == names
    for bench in benchmarks.values():
        for args in (bench.args, bench.quick or bench.args):
            script = REPO_ROOT / args[0]
            assert script.is_file(), f'{bench.name}: {args[0]} does not exist'
            text = script.read_text()
            for flag in (a for a in args[1:] if a.startswith('--')):
                assert f"'{flag}'" in text, f'{bench.name}: {args[0]} has no option {flag}'


def test_reproduce_line_parsing(tmp_path):
    """The Reproduce line is read with its arguments; nice and line breaks are dropped."""
    results = tmp_path / 'x.md'
    results.write_text('# x\n\nReproduce: `nice -n 10 python bench/diagnosis_stats.py --seeds 3\n'
                       '  --scenarios a b --out bench/results/x` (from the root)\n')
    assert run_all.reproduce_line(results) == [
        'bench/diagnosis_stats.py', '--seeds', '3', '--scenarios', 'a', 'b', '--out',
        'bench/results/x']
    results.write_text('# y\n\nno command here\n')
    assert run_all.reproduce_line(results) is None


def test_short_selection_leaves_out_the_long_studies(capsys):
    """--skip-long --list names the short benchmarks only, and exits 0."""
    assert run_all.main(['--skip-long', '--list']) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    benchmarks, _ = run_all.registry()
    assert listed == [n for n, b in benchmarks.items() if not b.long]
    assert 'diagnose_speed' in listed and 'process_noise' not in listed


def test_workers_override_reaches_only_the_studies_that_take_it(capsys):
    """--workers 1 replaces or adds the worker count of the statistical studies, nothing else."""
    assert run_all.main(['--list', '--workers', '1']) == 0
    commands = {line.split()[0]: line.split()[2:] for line in capsys.readouterr().out.splitlines()}
    benchmarks, _ = run_all.registry()
    for name, words in commands.items():
        if benchmarks[name].workers:
            assert words[words.index('--workers') + 1] == '1', name
            assert words.count('--workers') == 1, name
    assert 'adequacy' in commands and benchmarks['adequacy'].workers
    speed = commands['monte_carlo_speed']        # its timing on 2 cores is the figure
    assert speed[speed.index('--workers') + 1] == '2'


def test_notes_survive_a_rewrite(tmp_path):
    """Notes after NOTES_MARK come back when a benchmark rewrites its file without them."""
    results = tmp_path / 'x.md'
    results.write_text(f'# x\n\nold table\n\n{run_all.NOTES_MARK}\nReading: it is fast.\n')
    notes = run_all.notes_of(results)
    assert notes.startswith(run_all.NOTES_MARK) and 'it is fast' in notes
    results.write_text('# x\n\nnew table\n')           # what the benchmark writes
    assert run_all.keep_notes(results, notes)
    assert results.read_text() == f'# x\n\nnew table\n\n{notes}'
    assert not run_all.keep_notes(results, notes)     # already there: not twice
    assert run_all.notes_of(tmp_path / 'missing.md') == ''
