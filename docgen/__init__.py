"""Generated documentation: results tables, task spec pages and task pictures.

``python -m docgen`` writes the generated files (the README's results block, docs/results.md,
docs/tasks/*.md); ``python -m docgen --check`` says which are out of date;
``python -m docgen.pictures`` renders docs/images/*.png. Not part of the installed package.
"""
