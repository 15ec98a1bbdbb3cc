import json

import pytest

from benchmarks.bench_render import main


def test_one_configuration_renders_the_seeds_with_the_version_asked_for(capsys):
    for version in (1, 3):
        main(["--one", "--sizes", "32", "--workers", "1", "--scenes", "2", "--views", "2", "--versions", str(version)])
        pairs, views, seconds, cpu, nbytes, recorded = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert views == 4 and pairs >= 1 and seconds > 0 and cpu > 0 and nbytes > 0 and recorded == version


def test_an_unknown_generator_version_is_refused_naming_the_known_ones(capsys):
    with pytest.raises(SystemExit):
        main(["--versions", "2", "9"])
    assert "--versions expected generator versions of (1, 2, 3), got [2, 9]" in capsys.readouterr().err
