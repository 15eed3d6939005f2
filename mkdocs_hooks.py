"""MkDocs hooks of the manual (mkdocs.yml ``hooks``): the generated pages are built from the code at hand, never
committed, so they cannot drift (denoisers.manual)."""
from __future__ import annotations

from mkdocs.structure.files import File, Files

from denoisers.manual import CONFIG_REFERENCE_PAGE, ISIK_TRAINING_PAGE, config_reference, paper_pages, \
    training_progress_page


def on_files(files: Files, config) -> Files:
    """Add ``configuration-reference.md``, generated from the config's JSON schema, the paper pages
    (``papers/*.md`` with their figures), generated from the published run, and the Isik run's training progress,
    generated from the store."""
    files.append(File.generated(config, CONFIG_REFERENCE_PAGE, content=config_reference()))
    files.append(File.generated(config, ISIK_TRAINING_PAGE, content=training_progress_page()))
    for path, content in paper_pages().items():
        files.append(File.generated(config, path, content=content))
    return files
