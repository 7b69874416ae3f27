"""Sphinx configuration of the maniskill_torchrl docs (``make docs``)."""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.abspath(".."))
sys.path.insert(0, os.path.abspath("_ext"))  # curves: the pictures of curves.md, drawn from benchmarks/ at build time

import maniskill_torchrl  # noqa: E402

project = "maniskill_torchrl"
author = "maniskill_torchrl contributors"
copyright = "maniskill_torchrl contributors, Apache-2.0"
release = version = maniskill_torchrl.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "curves",
]

source_suffix = {".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build"]

myst_enable_extensions = ["colon_fence", "deflist"]
# GitHub-style anchors for headings, so links such as guides/gpu.md#some-heading resolve.
myst_heading_anchors = 4

autodoc_member_order = "bysource"
# Only the library's own docstrings: an override of a TorchRL / gymnasium method without one of
# its own is not listed with the base class's text.
autodoc_inherit_docstrings = False
autodoc_typehints = "signature"
autodoc_class_signature = "mixed"
autodoc_default_options = {"members": True, "show-inheritance": True}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
# One field list per section, names in bold: "a, b, c: as in X" (several arguments on one line)
# then reads as written, and the types stay text rather than references.
napoleon_use_param = False
napoleon_use_rtype = False
napoleon_use_keyword = False

# Warnings are errors (make docs: -W --keep-going) and every reference is checked (nitpicky),
# except references into other projects: no inventory of theirs can be fetched here, so names
# from the standard library, torch, TorchRL, tensordict, gymnasium, numpy and ManiSkill are
# taken as they are. A broken reference to this library's own names fails the build.
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(torch|torchrl|tensordict|gymnasium|gym|numpy|np|mani_skill|sapien|h5py|ray)(\..*)?"),
    (r"py:.*", r"(typing|collections|os|pathlib|multiprocessing|concurrent|enum|abc|types)\..*"),
    (
        r"py:class",
        r"(int|float|str|bool|bytes|object|dict|list|tuple|set|type|slice|Callable|Sequence"
        r"|Mapping|Iterable|Iterator|Any|Path|Literal|Ellipsis|EllipsisType|NoneType|optional)",
    ),
    (r"py:exc", r"[A-Za-z]+(Error|Exception|Warning)"),
    # Third-party names that the code imports under TYPE_CHECKING (string annotations).
    (r"py:class", r"(BaseEnv|NestedKey|TensorSpec|Composite|TensorDictBase|TensorDict|EnvBase|Transform)"),
]


# The public classes are documented where users import them (``maniskill_torchrl.ActionRepeat``,
# ``maniskill_torchrl.CPUVectorEnv``), while docstrings also name them by the modules that define
# or re-export them (``maniskill_torchrl.transforms.ActionRepeat``): those references resolve to
# the documented object. A reference to a member that a class inherits from another project
# (``EnvBase.set_seed``, ``gym.Wrapper.env``, ``ReplayBuffer.sample``) is taken as it is, as the
# references into other projects above are.
def _aliases() -> dict[str, str]:
    import importlib

    aliases = {}
    for name, module in maniskill_torchrl._EXPORTS.items():
        obj = getattr(importlib.import_module(module), name)
        for path in (module, obj.__module__, "maniskill_torchrl.transforms"):
            aliases[f"{path}.{name}"] = f"maniskill_torchrl.{name}"
    return aliases


def _inherited_from_elsewhere(node) -> bool:
    import importlib

    cls_name, target = node.get("py:class"), node.get("reftarget", "")
    module = node.get("py:module")
    if not cls_name or not module or "." in target:
        return False
    try:
        cls = getattr(importlib.import_module(module), cls_name.split(".")[0])
    except (ImportError, AttributeError):
        return False
    for base in getattr(cls, "__mro__", ()):
        if target in vars(base):
            return not base.__module__.startswith("maniskill_torchrl")
    return False


def _missing_reference(app, env, node, contnode):
    if node.get("refdomain") != "py":
        return None
    target = node.get("reftarget", "")
    aliases = app.config._maniskill_aliases
    for alias, canonical in aliases.items():
        if target == alias or target.startswith(alias + "."):
            domain = env.get_domain("py")
            return domain.resolve_xref(
                env, node["refdoc"], app.builder, node["reftype"], canonical + target[len(alias) :], node, contnode
            )
    if _inherited_from_elsewhere(node):
        return contnode
    return None


def _init_signature(app, what, name, obj, options, signature, return_annotation):
    # TorchRL's envs and transforms have a metaclass whose __call__(*args, **kwargs) autodoc would
    # show as the class's signature: show __init__'s instead.
    if what == "class" and signature == "(*args, **kwargs)":
        from sphinx.util.inspect import signature, stringify_signature

        sig = signature(obj.__init__, bound_method=True)  # without self; string annotations evaluated
        return stringify_signature(sig, show_return_annotation=False), return_annotation
    return None


_PUBLIC_MODULES = ["maniskill_torchrl", "maniskill_torchrl.wrappers", "maniskill_torchrl.data"]


def _documented_library_classes() -> set[str]:
    import importlib

    return {n for m in _PUBLIC_MODULES for n in getattr(importlib.import_module(m), "__all__", [])}


def _public_bases(app, name, obj, options, bases):
    # Private bases (TorchRL's _EnvWrapper) say nothing to a reader. When every base is
    # private, the first public class up the MRO (TorchRL's EnvBase) stands in.
    documented = _documented_library_classes()

    def public(b):
        if b.__name__.startswith("_"):
            return False
        return not b.__module__.startswith("maniskill_torchrl") or b.__name__ in documented

    kept = [b for b in bases if public(b)]
    if bases and not kept:
        kept = [next(b for b in obj.__mro__[1:] if public(b))]
    bases[:] = kept


def _skip_members_of_other_projects(app, what, name, obj, skip, options):
    # A class documented with :inherited-members: (ManiSkillEnv, whose get_state / render come
    # from ManiSkillWrapper) lists what the library defines, not TorchRL's or torch's.
    inherited = getattr(options, "inherited_members", None)
    if inherited is None and hasattr(options, "get"):
        inherited = options.get("inherited_members")
    if what != "class" or not inherited:
        return None
    fn = getattr(obj, "fget", obj)
    fn = getattr(fn, "__func__", fn)
    if not (getattr(fn, "__module__", None) or "").startswith("maniskill_torchrl"):
        return True
    return None


def _fix_viewcode_backlinks(app, exception) -> None:
    # viewcode keeps one module name per source page (the first documented object's: maniskill_torchrl for
    # engines/cpu_vector.py, whose CPUVectorEnv is documented at the top level) and links each function's
    # "[docs]" to <that name>.<function>: a function documented under its own module
    # (maniskill_torchrl.engines.cpu_vector.in_process_default) gets an anchor that exists nowhere. Each such
    # link is pointed at the object as documented.
    import re
    from pathlib import Path

    if exception is not None or app.builder.format != "html":
        return
    objects = app.env.get_domain("py").objects
    for page in Path(app.outdir, "_modules").rglob("*.html"):
        modname = page.relative_to(Path(app.outdir, "_modules")).with_suffix("").as_posix().replace("/", ".")
        html = page.read_text()

        def fix(m: re.Match, modname: str = modname) -> str:
            target = m.group(2)
            name = target.rsplit(".", 1)[-1]
            if target in objects or f"{modname}.{name}" not in objects:
                return m.group(0)
            return f"{m.group(1)}{modname}.{name}{m.group(3)}"

        fixed = re.sub(r'(class="viewcode-back" href="[^"#]*#)([^"]+)(")', fix, html)
        if fixed != html:
            page.write_text(fixed)


def setup(app):
    app.connect("build-finished", _fix_viewcode_backlinks)
    app.config._maniskill_aliases = _aliases()
    app.connect("missing-reference", _missing_reference)
    app.connect("autodoc-process-signature", _init_signature)
    app.connect("autodoc-process-bases", _public_bases)
    app.connect("autodoc-skip-member", _skip_members_of_other_projects)


html_theme = "furo"
html_title = f"maniskill_torchrl {release}"
