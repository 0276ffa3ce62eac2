"""Parallel gzip: pieces deflated on every core form one gzip member that any reader decodes
to the original bytes, about as small as one stream."""

from __future__ import annotations

import gzip
import zlib

import numpy as np
import orjson
import pytest

from service.http.compression import PARALLEL_MINIMUM, gzip_parallel
from tests.helpers.meshes import icosphere
from tests.helpers.service import forms_json


def _mesh_json(n: int) -> bytes:
    rng = np.random.default_rng(n)
    return orjson.dumps({"vertices": rng.normal(size=(n, 3)),
                         "faces": rng.integers(0, n, (2 * n, 3))},
                        option=orjson.OPT_SERIALIZE_NUMPY)


@pytest.mark.parametrize("pieces", [1, 2, 3, 7])
@pytest.mark.parametrize("size", [0, 1, 1000, 40_000, 300_000])
def test_gzip_parallel_decodes_to_the_body(pieces, size):
    body = _mesh_json(20_000)[:size]
    packed = gzip_parallel(body, 1, pieces)
    assert gzip.decompress(packed) == body
    stream = zlib.decompressobj(16 + zlib.MAX_WBITS)
    assert stream.decompress(packed) == body and stream.eof and not stream.unused_data


def test_gzip_parallel_is_as_small_as_one_stream():
    body = _mesh_json(30_000)
    one, four = gzip.compress(body, 1, mtime=0), gzip_parallel(body, 1, 4)
    assert abs(len(four) - len(one)) < 0.01 * len(one), (len(four), len(one))
    text = b"abc" * 200_000  # highly repetitive: each piece is primed with the one before
    assert len(gzip_parallel(text, 6, 4)) < 2 * len(gzip.compress(text, 6))


def test_large_response_is_one_gzip_member(client):
    body = forms_json(*icosphere(5))
    plain = client.post("/v1/reconstruct", json=body, headers={"accept-encoding": "identity"})
    assert plain.status_code == 200 and len(plain.content) > PARALLEL_MINIMUM
    with client.stream("POST", "/v1/reconstruct", json=body,
                       headers={"accept-encoding": "gzip"}) as response:
        assert response.headers["content-encoding"] == "gzip"
        packed = b"".join(response.iter_raw())
    assert int(response.headers["content-length"]) == len(packed) < len(plain.content) / 2
    doc, expected = orjson.loads(gzip.decompress(packed)), plain.json()
    assert doc["vertices"] == expected["vertices"] and doc["faces"] == expected["faces"]
    assert doc["report"].keys() == expected["report"].keys()  # its timings differ per call
