"""Stand-in for einops.rearrange / einops.repeat: named axes, parenthesised groups, '1' and '...'.

Enough for the patterns the official Epona code uses (see training/stand_ins/README.md)."""
import math

import torch


def _parse(side):
    groups, i, tokens = [], 0, side.replace("(", " ( ").replace(")", " ) ").split()
    while i < len(tokens):
        if tokens[i] == "(":
            j = tokens.index(")", i)
            groups.append(tokens[i + 1:j])
            i = j + 1
        else:
            groups.append([tokens[i]])
            i += 1
    return groups


def _sizes(groups, shape, known):
    if sum(g == ["..."] for g in groups) > 1:
        raise ValueError("one ellipsis at most")
    ell = [k for k, g in enumerate(groups) if g == ["..."]]
    n_fixed = len(groups) - len(ell)
    if (not ell and n_fixed != len(shape)) or len(shape) < n_fixed:
        raise ValueError(f"pattern has {len(groups)} groups, tensor has {len(shape)} dims")
    sizes, dims = dict(known), list(shape)
    expanded = []
    for g in groups:
        if g == ["..."]:
            n = len(shape) - n_fixed
            names = [f"...{k}" for k in range(n)]
            for name in names:
                sizes[name] = dims.pop(0)
            expanded.append(names)
            continue
        total = dims.pop(0)
        unknown = [a for a in g if a not in sizes and a != "1"]
        prod = math.prod(sizes[a] for a in g if a in sizes)
        if len(unknown) > 1:
            raise ValueError(f"cannot infer {unknown}")
        if unknown:
            sizes[unknown[0]] = total // prod
        expanded.append([a for a in g if a != "1"])
    return sizes, expanded


def _expand_out(groups, sizes):
    out = []
    for g in groups:
        if g == ["..."]:
            out.extend([k] for k in sorted((k for k in sizes if k.startswith("...")), key=lambda s: int(s[3:])))
        else:
            out.append([a for a in g if a != "1"])
    return out


def _apply(tensor, pattern, allow_new, **known):
    left, right = (s.strip() for s in pattern.split("->"))
    lg, rg = _parse(left), _parse(right)
    sizes, lexp = _sizes(lg, tuple(tensor.shape), known)
    flat_in = [a for g in lexp for a in g]
    x = tensor.reshape([sizes[a] for a in flat_in]) if flat_in else tensor.reshape(())
    rexp = _expand_out(rg, sizes)
    flat_out = [a for g in rexp for a in g]
    new = [a for a in flat_out if a not in flat_in]
    if new and not allow_new:
        raise ValueError(f"new axes {new} in rearrange")
    x = x.permute([flat_in.index(a) for a in flat_out if a in flat_in])
    if new:  # repeat: insert and expand the new axes
        shape = [sizes[a] if a in flat_in else 1 for a in flat_out]
        x = x.reshape(shape).expand([sizes[a] for a in flat_out])
    final = [math.prod(sizes[a] for a in g) if g else 1 for g in rexp]
    return x.reshape(final)


def rearrange(tensor, pattern, **axes):
    return _apply(tensor, pattern, False, **axes)


def repeat(tensor, pattern, **axes):
    return _apply(tensor, pattern, True, **axes)
