"""MkDocs hooks of the manual (mkdocs.yml ``hooks``): the generated pages are built from the code at hand, never
committed, so they cannot drift (denoisers.manual)."""
from __future__ import annotations

from mkdocs.structure.files import File, Files

from denoisers.manual import CONFIG_REFERENCE_PAGE, config_reference, paper_pages


def on_files(files: Files, config) -> Files:
    """Add ``configuration-reference.md``, generated from the config's JSON schema, and the paper pages
    (``papers/*.md`` with their figures), generated from the published run."""
    files.append(File.generated(config, CONFIG_REFERENCE_PAGE, content=config_reference()))
    for path, content in paper_pages().items():
        files.append(File.generated(config, path, content=content))
    return files
