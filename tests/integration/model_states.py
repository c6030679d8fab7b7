"""Shared by the crash and fault tests: small real models, and what version of a model a
directory holds (for "exactly the old or the new version, and no orphans")."""

import hashlib
import os
import re
import subprocess

import numpy as np
from osgeo import gdal

from check_import import Failures, find_ci, hidden_file, read_hierarchy
from harness import write_raster
from merge_check import NONCE, folder_digest

gdal.UseExceptions()

TEMP = re.compile(r"\..+\.tmp-[0-9]+-[0-9]+")
# A kept revision's hierarchy (docs: core/store/README.md), and the record of a revision in a
# hierarchy: when and by which job differ between two runs of the same write.
REVISION_FILE = re.compile(r"vsm-revision-([0-9]+)\.xml")
# The index of a hierarchy file (core/opc/README.md, "The index"): "patchhierarchy.vsmidx" beside the hierarchy,
# "vsm-revision-N.vsmidx" beside a kept revision's; one beside no hierarchy file is an orphan.
INDEX_FILE = re.compile(r"(patchhierarchy|vsm-revision-[0-9]+)\.vsmidx")
# A base of delta indexes (a full index a delta builds on): not an orphan while an index beside a
# hierarchy file names it (its name is in that index's bytes).
INDEX_BASE = re.compile(r"vsm-index-base-[0-9]+-[0-9a-f]{8}\.vsmidx")
PARENT = re.compile(rb"<Revision>\s*<Parent>([0-9]+)</Parent>")
VERSIONED = re.compile(r"[0-9]+_[0-9]+_[0-9]+-v([0-9]+)(?:-[0-9a-f]{8})?")
REVISION_RECORD = re.compile(rb"<Revision>.*?</Revision>", re.S)
# The second hierarchy file of hidden levels (core/opc/README.md): a new random name per write, so
# a version is told by its content.
HIDDEN_LEVELS = re.compile(rb"<HiddenLevels>([^<]*)</HiddenLevels>")
HIDDEN_FILE = re.compile(r"vsm-hidden-[0-9a-f]{16}\.xml")
LOCK = ".vsm-writer.lock"


def crop(source, out, lon0, lat0, lon1, lat1):
    gdal.Translate(out, source, projWin=[lon0, lat0, lon1, lat1])
    return out


def digest_tree(root):
    """{relative path: sha256} of every file under root but the writer lock."""
    files = {}
    for directory, _, names in os.walk(root):
        for name in names:
            if name == LOCK:
                continue
            path = os.path.join(directory, name)
            with open(path, "rb") as f:
                files[os.path.relpath(path, root)] = hashlib.sha256(f.read()).hexdigest()
    return files


def reachable_folders(opc, name="patchhierarchy.xml"):
    """The folders the hierarchy file `name` reaches from its root (hidden levels included)."""
    _, root, children = read_hierarchy(opc, name, hidden=True)
    reachable = set()
    stack = [root]
    while stack:
        folder = stack.pop()
        if folder in reachable:
            continue
        reachable.add(folder)
        stack.extend(children.get(folder, {}).values())
    return reachable


def revision_list(patches_dir, hierarchy, reachable):
    """What the model lists as its revisions: the parent the hierarchy's record names (None
    without a record) and the kept revision files older than the current version (the newest
    "-vN" of the folders it reaches; a copy of the current one, left by a write killed before its
    commit point, is not a revision of its own)."""
    parent = PARENT.search(hierarchy)
    current = max([int(m.group(1)) for m in map(VERSIONED.fullmatch, reachable) if m] or [1])
    kept = sorted(int(REVISION_FILE.fullmatch(e).group(1)) for e in os.listdir(patches_dir)
                  if REVISION_FILE.fullmatch(e))
    return (int(parent.group(1)) if parent else None, tuple(n for n in kept if n < current))


def version_of(opc):
    """((hierarchy bytes without the revision record, the revision list), {reachable folder:
    digest}, orphans): the revision list is revision_list's, so that a write killed at any moment
    leaves the old list or the new one;
    orphans are entries of Patches/ neither the hierarchy nor a kept revision reaches, tiles of
    Images/Diffuse none of them names, temporary files."""
    patches_dir = find_ci(opc, "Patches")
    with open(find_ci(patches_dir, "patchhierarchy.xml"), "rb") as f:
        text = f.read()
    reachable = reachable_folders(opc)

    def hidden_digest(match):
        with open(os.path.join(patches_dir, match.group(1).decode()), "rb") as f:
            return b"<HiddenLevels>%s</HiddenLevels>" % hashlib.sha256(
                NONCE.sub(rb"\1", f.read())).hexdigest().encode()

    hierarchy = (NONCE.sub(rb"\1", HIDDEN_LEVELS.sub(hidden_digest, REVISION_RECORD.sub(b"", text))),
                 revision_list(patches_dir, text, reachable))
    kept = set()
    for name in os.listdir(patches_dir):
        if REVISION_FILE.fullmatch(name):
            kept |= reachable_folders(opc, name)
    folders = {without_nonce(folder): folder_digest(os.path.join(patches_dir, folder), True)
               for folder in reachable}
    entries = os.listdir(patches_dir)
    indexes = [e for e in entries
               if INDEX_FILE.fullmatch(e) and INDEX_FILE.fullmatch(e).group(1) + ".xml" in entries]
    named_bases = set()
    for index in indexes:
        with open(os.path.join(patches_dir, index), "rb") as f:
            named_bases |= {m.decode() for m in
                            re.findall(INDEX_BASE.pattern.encode(), f.read(1 << 20))}
    named_hidden = {os.path.basename(hidden_file(opc, e) or "") for e in entries
                    if e.lower() == "patchhierarchy.xml" or REVISION_FILE.fullmatch(e)}
    orphans = sorted(e for e in entries
                     if e not in reachable | kept and e.lower() != "patchhierarchy.xml"
                     and not REVISION_FILE.fullmatch(e) and e not in indexes
                     and not (INDEX_BASE.fullmatch(e) and e in named_bases)
                     and not (HIDDEN_FILE.fullmatch(e) and e in named_hidden))
    tiles = os.path.join(opc, "Images", "Diffuse")
    if os.path.isdir(tiles):
        orphans += ["Images/Diffuse/" + t for t in sorted(os.listdir(tiles))
                    if t[:-4] not in reachable | kept]
    orphans += [e for e in os.listdir(opc) if TEMP.fullmatch(e)]
    return hierarchy, folders, orphans


def without_nonce(name):
    """A folder or file name with an edit's nonce left out."""
    return NONCE.sub(rb"\1", name.encode()).decode()


def which(version, old, new):
    if old is not None and version[:2] == old[:2]:
        return "old"
    if version[:2] == new[:2]:
        return "new"
    return None


def check_valid_and_reopened(vsm, where, outside, old, new, state, label, failures,
                             timeout=None):
    """After a failed or finished write that left `where` at `state` ("old" or "new"): `vsm
    validate` passes, and the next open for writing (a merge of `outside`, which fails as lying
    outside the target) changes no version and removes every orphan."""
    validate = subprocess.run([vsm, "validate", where], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True, timeout=timeout)
    if validate.returncode != 0:
        failures.append("%s: vsm validate: %s" % (label, validate.stdout[-400:]))
    reopen = subprocess.run([vsm, "merge", where, outside], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, timeout=timeout)
    if reopen.returncode != 1 or "outside" not in reopen.stderr:
        failures.append("%s: reopening: exit %d %s" % (label, reopen.returncode,
                                                       reopen.stderr[-300:]))
    after = version_of(where)
    if which(after, old, new) != state:
        failures.append("%s: reopening changed the version" % label)
    if after[2]:
        failures.append("%s: orphans after reopening: %s" % (label, after[2][:5]))


def make_outside_model(vsm, directory, patch_size):
    """A one-patch model in the Alps (10 E, 47 N), far outside any CONUS target."""
    tif = os.path.join(directory, "outside.tif")
    write_raster(tif, np.full((patch_size, patch_size), 1000.0), 10.0, 47.0, 1.0 / 3600)
    out = os.path.join(directory, "outside")
    subprocess.run([vsm, "import", tif, out, "--patch-size", str(patch_size)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return out


def assert_no_failures(test, failures):
    """The verdict of a sweep (a list of messages) as a unittest assertion, listed as
    check_import.Failures lists them."""
    listed = Failures()
    for message in failures:
        listed.add(message)
    listed.assert_none(test)
