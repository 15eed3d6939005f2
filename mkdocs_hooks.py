"""MkDocs hooks of the manual (mkdocs.yml ``hooks``): the generated pages are built from the code at hand, never
committed, so they cannot drift (denoisers.manual)."""
from __future__ import annotations

from mkdocs.structure.files import File, Files

from denoisers.manual import CONFIG_REFERENCE_PAGE, config_reference


def on_files(files: Files, config) -> Files:
    """Add ``configuration-reference.md``, generated from the config's JSON schema."""
    files.append(File.generated(config, CONFIG_REFERENCE_PAGE, content=config_reference()))
    return files
