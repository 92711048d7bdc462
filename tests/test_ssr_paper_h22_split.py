"""mehs paper's Table 2 says what its evaluation scored: split="auto" falls back to the val
split, or to every scene of a dataset built without held-out splits, and the title said
"(test split)" regardless."""

from mehs.ssr.paper import _scored


def test_table2_title_names_the_scored_split():
    assert _scored({"evaluations": {"main": {"scored": "test"}}}) == "test split"
    assert _scored({"evaluations": {"main": {"scored": "val"}}}).startswith("val split")
    assert _scored({"evaluations": {"main": {"scored": None}}}).startswith("every scene")
    assert _scored({"evaluations": {"main": {}}}) == "test split"     # a state of older runs
