"""
The package's import structure, read from the source with ast (no module is imported).

* No import cycle among rotor_id's modules, counting module-level and function-level imports
  alike (a function-level import hides a cycle from Python, not from the design).
* No private name (``_x``) imported from another module of the diagnosis, nor by it.
* The layers point one way: the adequacy check and the pipeline do not import the diagnosis.
* No function of the diagnosis is longer than about 80 lines, and none imports: the
  diagnosis's dependencies are all stated at the top of its modules.
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'rotor_id'


def _module_name(path):
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _modules():
    return {_module_name(p): p for p in PACKAGE.rglob('*.py')}


def _imports(path, modules):
    """Yield (imported module, names imported from it) of every import in a file."""
    package = _module_name(path)
    if path.name != '__init__.py':
        package = package.rpartition('.')[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules:
                    yield alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                up = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(up + ([base] if base else []))
            if base not in modules:
                continue
            names = []
            for alias in node.names:
                if f'{base}.{alias.name}' in modules:
                    yield f'{base}.{alias.name}', ()      # a submodule
                else:
                    names.append(alias.name)
            if names:
                yield base, tuple(names)


def _graph():
    modules = _modules()
    return {name: {m for m, _ in _imports(path, modules) if m != name}
            for name, path in modules.items()}


def _cycles(graph):
    """Return the strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_a_cycle_is_found_by_the_check():
    assert _cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]


def test_no_import_cycle_in_the_package():
    assert _cycles(_graph()) == []


def test_no_private_name_crosses_a_module():
    """A name with a leading underscore is imported, or passed as a keyword, only at home."""
    modules = _modules()
    crossing = []
    for name, path in modules.items():
        for imported, names in _imports(path, modules):
            private = [n for n in names if n.startswith('_')]
            if private and imported != name:
                crossing.append((name, imported, private))
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                crossing += [(name, 'keyword', kw.arg) for kw in node.keywords
                             if kw.arg and kw.arg.startswith('_')]
    assert crossing == []


def test_adequacy_and_pipeline_do_not_import_the_diagnosis():
    graph = _graph()
    for name in ('rotor_id.adequacy', 'rotor_id.pipeline', 'rotor_id.residuals'):
        assert not any(m.startswith('rotor_id.diagnosis') for m in graph[name]), name


#: "No function in diagnosis/ longer than about 80 lines": docstring included.
LONGEST_DIAGNOSIS_FUNCTION = 80


def test_no_long_function_in_the_diagnosis():
    long = []
    for path in sorted((PACKAGE / 'diagnosis').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > LONGEST_DIAGNOSIS_FUNCTION:
                    long.append(f'{path.name}:{node.lineno} {node.name} ({length} lines)')
    assert not long, long


def test_the_diagnosis_imports_at_module_level_only():
    inside = []
    for path in sorted((PACKAGE / 'diagnosis').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inside += [f'{path.name}:{sub.lineno} in {node.name}' for sub in ast.walk(node)
                           if isinstance(sub, (ast.Import, ast.ImportFrom))]
    assert not inside, inside
