#!/usr/bin/python3
"""Turn `perf script` output into a flame graph SVG (Python 3 standard library only).

Usage:
    perf script -i perf.data | tests/bench/flamegraph.py --title "vsm merge (b)" \\
        --out merge.svg [--collapsed merge.folded] [--top 25 --top-out top.txt]

Reads perf script's default output (from stdin, or a file given as argument) of a
recording with call graphs (`perf record -g` or `--call-graph dwarf`): per sample a
header line (comm pid[/tid] [cpu] time: period event:) and tab-indented frame lines
`addr symbol+0xoff (dso)`, leaf first.  Stacks are rooted at the comm (thread name)
and identical stacks are merged.  Symbols lose their offset, argument lists and long
template arguments (`<...>`); lambdas read `f::{lambda#N}`; unknown symbols show as
`[dso-basename]`.

  --out FILE        SVG, 1200 px wide, root at the bottom, frames < 0.1 % omitted
  --collapsed FILE  folded stacks, `comm;caller;...;leaf count` per line
  --top N           top-N tables (default 25) of self samples (the function holding
  --top-out FILE    the sampled IP, like `perf report --no-children`) and inclusive
                    samples (once per stack, comm excluded); '-' or none: stdout
Exit status 2 on unreadable input, zero samples or unwritable output.
"""

import argparse
import collections
import hashlib
import io
import re
import sys
from xml.sax.saxutils import escape

# header: comm pid[/tid] [cpu] time: [period] [event:] [ip sym (dso)]
HEADER_RE = re.compile(r'^(?P<comm>\S.*?)\s+-?\d+(?:/-?\d+)?\s+(?:\[\d+\]\s+)?'
                       r'\d+\.\d+:\s*(?P<rest>.*)$')
# frame: ip symbol[+0xoff] (dso); the dso is the last parenthesised group
_SYM_DSO = r'(?P<sym>.+?)\s+\((?P<dso>[^()]*(?: \(deleted\))?)\)\s*$'
FRAME_RE = re.compile(r'^\s*(?P<addr>[0-9a-fA-F]+)\s+' + _SYM_DSO)
HEADER_FRAME_RE = re.compile(r':\s+(?P<addr>[0-9a-fA-F]+)\s+' + _SYM_DSO)
# Names whose brackets are not argument or template lists (longest operators first).
PROTECT = [('(anonymous namespace)', '\x01')] + [
    ('operator' + op, 'operator' + chr(0xE000 + i)) for i, op in
    enumerate(['()', '<<=', '>>=', '<=>', '<<', '>>', '<=', '>=', '->*', '->', '<', '>'])]
MAX_TEMPLATE = 24      # template argument lists longer than this become <...>
WIDTH, FRAME_H, FONT, CHAR_W, PAD = 1200, 16, 12, 7, 10
MIN_FRACTION = 0.001   # frames narrower than 0.1 % of all samples are omitted


def die(msg):
    sys.stderr.write('flamegraph.py: error: %s\n' % msg)
    sys.exit(2)


def _strip(s, i, close):
    """Copy s[i:] up to the matching `close`, dropping (...) and shortening <...>."""
    out = []
    while i < len(s):
        c = s[i]
        if c == close:
            return ''.join(out), i + 1
        if c in '(<{':
            inner, i = _strip(s, i + 1, {'(': ')', '<': '>', '{': '}'}[c])
            inner = re.sub(r'\s+([,>])', r'\1', inner).strip()
            if c == '(' and out and out[-1] == ' ':     # function type: void (int)
                out[-1] = '()'
            elif c == '<':
                out.append('{lambda}' if inner == 'lambda' else
                           '<%s>' % (inner if len(inner) <= MAX_TEMPLATE else '...'))
            elif c == '{':
                out.append('{%s}' % inner)
            continue
        out.append(c)
        i += 1
    if close:
        raise ValueError('unbalanced')
    return ''.join(out), i


def shorten(sym):
    """Shorten a demangled C++ symbol moderately; plain C names pass unchanged."""
    sym = re.sub(r'\+0x[0-9a-fA-F]+$', '', sym.strip())
    if not any(c in sym for c in '(<{'):
        return sym
    s = sym
    for text, mark in PROTECT:
        s = s.replace(text, mark)
    try:
        s = _strip(s, 0, '')[0]
    except ValueError:
        return sym
    for text, mark in PROTECT:
        s = s.replace(mark, text)
    return s.replace('(anonymous namespace)', '(anon)').strip() or sym


def frame_name(sym, dso):
    if sym.startswith('[unknown]'):
        base = dso.replace(' (deleted)', '').rstrip('/').rsplit('/', 1)[-1]
        return '[%s]' % (base.strip('[]') or 'unknown')
    return shorten(sym)


def clean(name):
    """Make a name safe for the folded format (';' separates frames)."""
    return re.sub(r'[\x00-\x1f;]', '_', name)


def blocks(lines):
    """Group perf script lines into (header line, [frame lines]) per sample."""
    header, frames = None, []
    for line in lines:
        line = line.rstrip('\n')
        if line.startswith('#'):
            continue
        # Frames are tab-indented; headers may be space-padded (perf right-aligns the
        # comm when it prints no call graph).
        if line[:1] == '\t' or (line[:1] == ' ' and line.strip()
                                and not HEADER_RE.match(line.lstrip())):
            if header is not None:
                frames.append(line)
            continue
        if header is not None:
            yield header, frames
        header, frames = (line if line.strip() else None), []
    if header is not None:
        yield header, frames


def parse_sample(header, lines):
    """Return (stack root-first, self function) for one sample, or None.

    The self function is the one containing the sampled IP: among the leading frames
    sharing the leaf's address (inlined ones come first), the first that is not
    inlined, else the outermost inlined one.  This matches perf report's symbol.
    """
    m = HEADER_RE.match(header.lstrip())
    comm = m.group('comm') if m else header.split()[0]
    frames = [f for f in map(FRAME_RE.match, lines) if f]
    if not frames and m:                # no call graph: the frame is on the header
        frames = [f for f in [HEADER_FRAME_RE.search(m.group('rest'))] if f]
    if not frames and not m:            # unrecognised line without frames: skip
        return None
    names = [frame_name(f.group('sym'), f.group('dso')) for f in frames]
    own = comm
    for f, name in zip(frames, names):
        if f.group('addr') != frames[0].group('addr'):
            break
        own = name
        if f.group('dso') != 'inlined':
            break
    return [clean(n) for n in [comm] + names[::-1]], clean(own)


def color(name):
    """Warm colour derived deterministically from the name (as flamegraph.pl 'hot')."""
    h = hashlib.md5(name.encode('utf-8', 'replace')).digest()
    v1, v2, v3 = h[0] / 255.0, h[1] / 255.0, h[2] / 255.0
    return 'rgb(%d,%d,%d)' % (205 + int(50 * v3), int(230 * v1), int(55 * v2))


def build_tree(stacks):
    root = {'name': 'all', 'count': 0, 'kids': {}}
    for stack, n in stacks.items():
        root['count'] += n
        node = root
        for name in stack:
            node = node['kids'].setdefault(name, {'name': name, 'count': 0, 'kids': {}})
            node['count'] += n
    return root


def render_svg(stacks, title, total):
    root = build_tree(stacks)
    scale = (WIDTH - 2 * PAD) / float(total)
    rects, depth_max = [], 0
    todo = [(root, 0, 0)]           # (node, depth, x offset in samples)
    while todo:
        node, depth, x = todo.pop()
        if node['count'] < MIN_FRACTION * total:
            continue
        rects.append((node, depth, x))
        depth_max = max(depth_max, depth)
        for name in sorted(node['kids']):
            kid = node['kids'][name]
            todo.append((kid, depth + 1, x))
            x += kid['count']
    height = (depth_max + 1) * FRAME_H + 3 * PAD + 2 * FONT + 10
    out = ['<?xml version="1.0" standalone="no"?>',
           '<svg version="1.1" width="%d" height="%d" viewBox="0 0 %d %d" '
           'xmlns="http://www.w3.org/2000/svg">' % (WIDTH, height, WIDTH, height),
           '<style>text { font-family: Verdana, sans-serif; font-size: %dpx; }\n'
           'g:hover rect { stroke: black; stroke-width: 0.5; }</style>' % FONT,
           '<rect x="0" y="0" width="100%" height="100%" fill="rgb(248,248,232)"/>',
           '<text x="%d" y="%d" text-anchor="middle" style="font-size:%dpx">%s</text>'
           % (WIDTH // 2, PAD + FONT + 2, FONT + 5, escape(title)),
           '<text x="%d" y="%d" fill="rgb(100,100,100)">%d samples</text>'
           % (PAD, PAD + 2 * FONT + 10, total)]
    for node, depth, x in rects:
        n = node['count']
        x0, w = PAD + x * scale, n * scale
        y = height - PAD - (depth + 1) * FRAME_H
        label = '%s (%d samples, %.2f %%)' % (node['name'], n, 100.0 * n / total)
        chars = int((w - 6) // CHAR_W)
        text = node['name'] if len(node['name']) <= chars else (
            node['name'][:chars - 2] + '..' if chars >= 3 else '')
        out.append('<g><title>%s</title><rect x="%.1f" y="%d" width="%.1f" height="%d" '
                   'fill="%s" rx="2" ry="2"/>' % (escape(label), x0, y, w, FRAME_H - 1,
                                                  color(node['name'])))
        if text:
            out.append('<text x="%.1f" y="%d">%s</text>' % (x0 + 3, y + FRAME_H - 4,
                                                             escape(text)))
        out.append('</g>')
    out.append('</svg>')
    return '\n'.join(out) + '\n'


def top_tables(stacks, selfs, total, n):
    incl = collections.Counter()
    for stack, count in stacks.items():
        for name in set(stack[1:]):     # the comm root would trivially lead
            incl[name] += count

    def table(heading, counter):
        rows = ['%s (of %d samples)' % (heading, total),
                '%5s %9s %7s  %s' % ('rank', 'samples', 'percent', 'function')]
        ranked = sorted(counter.items(), key=lambda kv: (-kv[1], kv[0]))[:n]
        for i, (name, c) in enumerate(ranked, 1):
            rows.append('%5d %9d %6.2f%%  %s' % (i, c, 100.0 * c / total, name))
        return '\n'.join(rows) + '\n'

    return (table('Top %d by self samples' % n, selfs) + '\n'
            + table('Top %d by inclusive samples' % n, incl))


def write(path, text):
    try:
        if path == '-':
            sys.stdout.write(text)
        else:
            with open(path, 'w', encoding='utf-8') as f:
                f.write(text)
    except OSError as e:
        die('cannot write %s: %s' % (path, e.strerror or e))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('input', nargs='?', default='-', help='perf script text (default stdin)')
    ap.add_argument('--title', default='Flame Graph', help='title shown in the SVG')
    ap.add_argument('--out', required=True, help='SVG file to write')
    ap.add_argument('--collapsed', help='also write folded stacks to this file')
    ap.add_argument('--top', type=int, metavar='N', help='rows per top table (default 25)')
    ap.add_argument('--top-out', metavar='FILE', help="top tables file ('-' = stdout)")
    args = ap.parse_args()

    stacks, selfs = collections.Counter(), collections.Counter()
    try:
        if args.input == '-':
            if sys.stdin.isatty():
                die('no input: pipe `perf script` output in or name a file')
            src = io.TextIOWrapper(sys.stdin.buffer, encoding='utf-8', errors='replace')
        else:
            src = open(args.input, encoding='utf-8', errors='replace')
        with src:
            for sample in (parse_sample(h, f) for h, f in blocks(src)):
                if sample:
                    stacks[tuple(sample[0])] += 1
                    selfs[sample[1]] += 1
    except OSError as e:
        die('cannot read %s: %s' % (args.input, e.strerror or e))
    total = sum(stacks.values())
    if total == 0:
        die('no samples found in %s (is it `perf script` output?)'
            % ('stdin' if args.input == '-' else args.input))

    write(args.out, render_svg(stacks, args.title, total))
    if args.collapsed:
        write(args.collapsed, ''.join('%s %d\n' % (';'.join(s), c)
                                      for s, c in sorted(stacks.items())))
    if args.top is not None or args.top_out:
        write(args.top_out or '-', top_tables(stacks, selfs, total, args.top or 25))
    sys.stderr.write('flamegraph.py: %d samples, %d unique stacks -> %s\n'
                     % (total, len(stacks), args.out))


if __name__ == '__main__':
    main()
