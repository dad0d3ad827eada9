"""``python -m schema``: regenerate the committed JSON Schema ``schema/spec.schema.json``."""

from .json_schema import write_spec_json_schema

if __name__ == "__main__":
    print(write_spec_json_schema().name)
