#!/usr/bin/python3
"""Turn `perf script` output into a flame graph SVG (standard library only).

Usage:
    perf script -i perf.data | tests/bench/flamegraph.py --title "vsm merge (b)" \\
        --out merge.svg [--collapsed merge.folded] [--top 25 --top-out top.txt]

Input is perf script's default output of a recording made with call graphs
(`perf record -g` or `--call-graph dwarf`): a header line per sample (comm,
pid[/tid], [cpu], time, period, event) followed by indented frame lines
`<addr> <symbol+0xoff> (<dso>)`, leaf first, and a blank line between samples.
A sample without a call graph may carry its single frame on the header line.

Each stack is rooted at the comm (thread name); identical stacks are merged.
Symbols lose their `+0x...` offset and are shortened: argument lists in
parentheses are dropped, long template argument lists become `<...>`, and
lambdas read `f::{lambda#N}`.  Frames without a symbol are shown as
`[dso-basename]`.  Outputs:
  --out FILE        SVG flame graph, 1200 px wide, root at the bottom, frames
                    sorted alphabetically per level, frames < 0.1 % omitted.
  --collapsed FILE  folded stacks, `root;caller;...;leaf count` per line.
  --top N           tables of the N functions with the most self samples
  --top-out FILE    (function containing the sampled IP; inlined callees count
                    toward it, as in `perf report --no-children`) and the most
                    inclusive samples (counted once per stack, comm excluded).
                    Without --top-out the tables go to stdout.
An optional positional argument reads perf script text from a file instead of
stdin.  Exit status: 0 on success, 2 on unreadable input, zero samples or
unwritable output.
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
HEADER_FRAME_RE = re.compile(r':\s+[0-9a-fA-F]+\s+' + _SYM_DSO)
# Names whose brackets are not argument or template lists.
PROTECT = [('(anonymous namespace)', '\x01'), ('operator()', 'operator\x02'),
           ('operator<<=', 'operator\x03'), ('operator>>=', 'operator\x04'),
           ('operator<=>', 'operator\x05'), ('operator<<', 'operator\x06'),
           ('operator>>', 'operator\x07'), ('operator<=', 'operator\x0e'),
           ('operator>=', 'operator\x0f'), ('operator->*', 'operator\x10'),
           ('operator->', 'operator\x11'), ('operator<', 'operator\x12'),
           ('operator>', 'operator\x13')]
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
    for text, mark in reversed(PROTECT):
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


def parse(lines):
    """Yield (stack root-first, self function) per sample.

    The self function is the one containing the sampled IP: among the leading frames
    that share the leaf's address (inlined frames first), the first one that is not
    inlined, else the outermost inlined one.
    """
    comm, frames, self_fn, header_frame, self_open = None, [], None, None, False

    def finish():
        stack = frames or ([header_frame] if header_frame else [])
        own = self_fn or (stack[0] if stack else comm)
        return [clean(comm)] + [clean(f) for f in reversed(stack)], clean(own)

    for line in lines:
        line = line.rstrip('\n')
        if not line.strip():
            if comm is not None:
                yield finish()
            comm = None
            continue
        if line.startswith('#'):
            continue
        # Frames are tab-indented; headers may be space-padded (comm is right-aligned
        # when perf script prints no call graph).
        m = None if line[0] == '\t' else HEADER_RE.match(line.lstrip())
        if m is None and line[0] in ' \t':
            f = FRAME_RE.match(line)
            if comm is not None and f:
                name = frame_name(f.group('sym'), f.group('dso'))
                if not frames:
                    leaf_addr = f.group('addr')
                if self_open and f.group('addr') == leaf_addr:
                    self_fn, self_open = name, f.group('dso') == 'inlined'
                else:
                    self_open = False
                frames.append(name)
            continue
        if comm is not None:        # header directly after a sample without blank line
            yield finish()
        comm = m.group('comm') if m else line.split()[0]
        frames, self_fn, header_frame, self_open = [], None, None, True
        hf = HEADER_FRAME_RE.search(m.group('rest')) if m else None
        if hf:
            header_frame = frame_name(hf.group('sym'), hf.group('dso'))
    if comm is not None:
        yield finish()


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
            src = io.TextIOWrapper(sys.stdin.buffer, encoding='utf-8', errors='replace')
        else:
            src = open(args.input, encoding='utf-8', errors='replace')
        with src:
            for stack, own in parse(src):
                stacks[tuple(stack)] += 1
                selfs[own] += 1
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
