"""The Cosmos Policy ``/act`` wire protocol, shared by the client and the server.

It follows NVlabs/cosmos-policy ``cosmos_policy/experiments/robot/aloha/deploy.py``:

* ``POST /act`` with a JSON body whose numpy arrays are encoded by ``json_numpy``
  (``{"__numpy__": <base64>, "dtype": ..., "shape": [...]}``). Request fields: ``primary_image``,
  ``left_wrist_image``, ``right_wrist_image`` (uint8 (H, W, 3), all three required), ``proprio``
  (float32 (P,)) and ``task_description`` (str); a RoboCasa-style server reads ``primary_image``,
  ``secondary_image`` and ``wrist_image`` instead (the client's profiles pick the set). A body ``{"encoded": "<json_numpy string>"}`` (the
  "double-encoded" form for clients without json_numpy) is accepted too.
  A request may also carry ``return_all_query_results`` (bool) and fields a server may ignore (upstream's eval
  client sends ``proprio_history`` / ``images_history``); :func:`decode_request` keeps those in ``extra``.
* The answer is a dict with ``actions`` (a list of (A,) rows, or an (H, A) array),
  ``future_image_predictions`` (a dict ``future_image`` / ``future_wrist_image`` / ``future_wrist_image2``
  -> uint8 (h, w, 3), or None for a view the model does not predict) and ``value_prediction`` (float).
  Upstream's robot client (``run_aloha_eval.py``, ``get_action_from_server``) reads ``value_predictions``
  (plural), so :func:`encode_response` sends both keys (``VALUE_KEYS``), and the ``all_*`` lists when asked for
  all query results. An ``{"encoded": ...}`` request is answered double-encoded (a JSON string holding the
  json_numpy text), as upstream answers it.
* On any failure the server answers the JSON string ``"error"`` with HTTP 200; there is no health route.
* wamplan's servers add a ``wamplan`` field (``WAMPLAN_FIELD``) to an answer: a dict saying what they did to the
  request or the answer (``notes``: one line each), and whatever a planning proxy reports; clients that do not
  know it ignore it.

wamplan's servers add what a real deployment needs, outside the protocol (:mod:`wamplan.serving`): an optional
shared secret, a request size limit (HTTP 413) and ``GET /health``; those refusals are HTTP 401 / 413 with a
one-line ``{"error": ...}``, and so are its failures (400 a malformed request, 422 one the WAM refuses, 500 a
failure of the WAM), unless started in the ``upstream`` error mode, which answers every failure as upstream does.
A server maps request fields to cameras and cameras to response fields (:func:`resolve_maps`), checks the proprio
against its model's size (:func:`fit_proprio`) and clips actions into [-1, 1] (:func:`clip_actions`).

Decoders raise :class:`ProtocolError` (malformed message) or :class:`ErrorReply` (the ``"error"`` answer);
callers turn those into errors for people, naming the server.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import json_numpy
import numpy as np

from wamplan.errors import UserError
from wamplan.serving import ERROR_REPLY

ROUTE = "/act"
DEFAULT_PORT = 8777
REQUEST_IMAGE_FIELDS = ("primary_image", "left_wrist_image", "right_wrist_image")  # ALOHA's deploy script
# A RoboCasa/LIBERO-style model reads two third-person views and one wrist view under these names.
ROBOCASA_REQUEST_IMAGE_FIELDS = ("primary_image", "secondary_image", "wrist_image")
REQUEST_IMAGE_FIELD_SETS = (REQUEST_IMAGE_FIELDS, ROBOCASA_REQUEST_IMAGE_FIELDS)
# The fields Cosmos Policy fills for a 3-camera (ALOHA-style) model; RoboCasa models add future_image2.
RESPONSE_IMAGE_FIELDS = ("future_image", "future_wrist_image", "future_wrist_image2")
KNOWN_RESPONSE_IMAGE_FIELDS = RESPONSE_IMAGE_FIELDS + ("future_image2",)
JSON_HEADERS = {"Content-Type": "application/json"}
# Upstream's server sends the first, its robot client reads the second: an answer carries both.
VALUE_KEYS = ("value_prediction", "value_predictions")
# The value sent for a model without a value head (upstream's best-of-N reads a missing value as 0.0).
VALUE_STANDIN = 0.0
WAMPLAN_FIELD = "wamplan"
RETURN_ALL_FIELD = "return_all_query_results"
# The request fields every request carries besides its images; anything else is a request's ``extra``.
_REQUEST_KEYS = ("proprio", "task_description", RETURN_ALL_FIELD)
_ANSWER_KEYS = ("actions", "future_image_predictions", *VALUE_KEYS, WAMPLAN_FIELD)


class ProtocolError(ValueError):
    """A request or answer does not follow the /act protocol; the message says what is wrong."""


class ErrorReply(Exception):
    """The server answered the string "error": it failed while handling the request."""


@dataclass
class ActRequest:
    images: dict[str, np.ndarray]  # request field -> (H, W, 3) uint8
    proprio: np.ndarray  # (P,) float32
    task_description: str
    return_all: bool = False  # return_all_query_results: add the all_* lists to the answer
    encoded: bool = False  # the request came as {"encoded": ...}: answer double-encoded
    extra: dict[str, Any] = field(default_factory=dict)  # the request's other fields, decoded json_numpy values


@dataclass
class ActResponse:
    actions: np.ndarray  # (H, A) float32, finite
    future_images: dict[str, np.ndarray]  # response field -> (h, w, 3) uint8; views left out are absent
    value: float | None = None  # None: the model predicts none (sent as VALUE_STANDIN, said in the wamplan field)
    extra: dict[str, Any] = field(default_factory=dict)  # the answer's other fields (e.g. upstream's all_* lists)
    wamplan: dict[str, Any] = field(default_factory=dict)  # the WAMPLAN_FIELD: notes, a proxy's report


def _loads(body: bytes | str, what: str) -> Any:
    try:
        return json_numpy.loads(body)
    except (ValueError, TypeError, KeyError) as e:  # bad JSON, bad base64, size/shape mismatch
        raise ProtocolError(f"the {what} is not valid json_numpy JSON ({type(e).__name__}: {e})") from e
    except RecursionError:  # arrays or objects nested past the parser's depth
        raise ProtocolError(f"the {what} nests JSON arrays or objects too deeply to parse; send the protocol's "
                            f"flat fields") from None


def _image(x: Any, what: str) -> np.ndarray:
    """A (h, w, 3) uint8 copy of ``x``; a leading batch axis of 1 is dropped."""
    if isinstance(x, list):
        try:
            x = np.asarray(x)
        except ValueError as e:
            raise ProtocolError(f"{what} is a ragged list, not an image") from e
    if not isinstance(x, np.ndarray):
        raise ProtocolError(f"{what} is a {type(x).__name__}, not an image array")
    if x.ndim == 4 and x.shape[0] == 1:
        x = x[0]  # (1, h, w, 3) -> (h, w, 3)
    if x.ndim != 3 or x.shape[2] != 3 or min(x.shape[:2]) < 1:
        raise ProtocolError(f"{what} has shape {x.shape}, expected (h, w, 3)")
    if x.dtype != np.uint8:
        if not np.issubdtype(x.dtype, np.integer) or x.min() < 0 or x.max() > 255:
            raise ProtocolError(f"{what} has dtype {x.dtype}, expected uint8")
        x = x.astype(np.uint8)
    return np.array(x, dtype=np.uint8, copy=True)  # json_numpy arrays are read-only views


def _numbers(x: Any, what: str, ndim: int) -> np.ndarray:
    """A finite float32 array of ``ndim`` dims from an array or (nested) list of numbers."""
    try:
        arr = np.array(x, dtype=np.float32)
    except (ValueError, TypeError) as e:
        raise ProtocolError(f"{what} is not a numeric array ({e})") from e
    if arr.ndim == ndim + 1 and arr.shape[0] == 1:
        arr = arr[0]  # drop a batch axis of 1
    if arr.ndim != ndim or arr.size == 0:
        raise ProtocolError(f"{what} has shape {arr.shape}, expected {ndim} non-empty dimension(s)")
    if not np.isfinite(arr).all():
        raise ProtocolError(f"{what} holds non-finite values ({int((~np.isfinite(arr)).sum())} NaN/inf)")
    return arr


as_image = _image  # (x, what) -> (h, w, 3) uint8 copy, or ProtocolError naming ``what``
as_numbers = _numbers  # (x, what, ndim) -> finite float32 array, or ProtocolError naming ``what``


def encode_request(req: ActRequest) -> str:
    """The JSON body of ``POST /act`` (the image fields are those of ``req.images``, then ``req.extra``);
    ``req.encoded``: the double-encoded form ``{"encoded": "<json_numpy text>"}``."""
    payload = dict(req.extra)
    payload.update({name: np.ascontiguousarray(img, dtype=np.uint8) for name, img in req.images.items()})
    payload["proprio"] = np.ascontiguousarray(req.proprio, dtype=np.float32)  # (P,)
    payload["task_description"] = str(req.task_description)
    if req.return_all:
        payload[RETURN_ALL_FIELD] = True
    text = json_numpy.dumps(payload)
    return json.dumps({"encoded": text}) if req.encoded else text


def decode_request(body: bytes | str, image_fields: tuple[str, ...] = REQUEST_IMAGE_FIELDS) -> ActRequest:
    """Parse and check a request body (server side) that must carry ``image_fields``."""
    payload = _loads(body, "request body")
    encoded = isinstance(payload, Mapping) and "encoded" in payload
    if encoded:  # double-encoded form; upstream's server allows no other key beside it
        if len(payload) != 1:
            raise ProtocolError(f"an 'encoded' request carries only 'encoded', got also {sorted(set(payload) - {'encoded'})}")
        if not isinstance(payload["encoded"], str):
            raise ProtocolError(f"'encoded' is a {type(payload['encoded']).__name__}, expected a json_numpy string")
        payload = _loads(payload["encoded"], "'encoded' request payload")
    return request_from_payload(payload, image_fields, encoded=encoded)


def request_from_payload(payload: Any, image_fields: tuple[str, ...] = REQUEST_IMAGE_FIELDS,
                         encoded: bool = False) -> ActRequest:
    """Check a decoded request (a mapping of the protocol's fields, however it travelled) that must carry
    ``image_fields``; ``encoded``: it came double-encoded (answer it so)."""
    if not isinstance(payload, Mapping):
        raise ProtocolError(f"the request is a {type(payload).__name__}, expected an object of the protocol's fields")
    missing = [k for k in (*image_fields, "proprio", "task_description") if k not in payload]
    if missing:
        raise ProtocolError(f"the request lacks field(s) {missing}")
    images = {k: _image(payload[k], f"request field '{k}'") for k in image_fields}
    shapes = {k: img.shape for k, img in images.items()}
    first = next(iter(shapes), None)
    odd = [k for k in shapes if shapes[k] != shapes[first]]
    if odd:  # a WAM stacks its views: one size for all
        raise ProtocolError(f"request field '{odd[0]}' has shape {shapes[odd[0]]} but '{first}' has "
                            f"{shapes[first]}; send every view at one size")
    proprio = _numbers(payload["proprio"], "request field 'proprio'", ndim=1)  # (P,)
    task = payload["task_description"]
    if not isinstance(task, str):
        raise ProtocolError(f"request field 'task_description' is a {type(task).__name__}, expected a string")
    return_all = payload.get(RETURN_ALL_FIELD, False)
    if return_all is None:
        return_all = False
    if not isinstance(return_all, (bool, np.bool_)) and return_all not in (0, 1):
        raise ProtocolError(f"request field '{RETURN_ALL_FIELD}' is {return_all!r}, expected true or false")
    extra = {k: v for k, v in payload.items() if k not in image_fields and k not in _REQUEST_KEYS}
    return ActRequest(images=images, proprio=proprio, task_description=task, return_all=bool(return_all),
                      encoded=encoded, extra=extra)


def encode_response(resp: ActResponse, *, all_query_results: bool = False, double_encode: bool = False) -> str:
    """The JSON answer, shaped like Cosmos Policy's (actions as a list of (A,) rows), that upstream's robot
    client parses (:func:`response_payload`); with ``double_encode`` as a JSON string holding the json_numpy text
    (upstream's answer to an ``encoded`` request)."""
    answer = response_payload(resp, all_query_results=all_query_results)
    rows = [row for row in answer["actions"]]  # H x (A,)
    answer["actions"] = rows
    if all_query_results:
        answer.update(all_actions=[rows], all_actions_by_depth=[[rows]])
    text = json_numpy.dumps(answer)
    return json.dumps(text) if double_encode else text


def response_payload(resp: ActResponse, *, all_query_results: bool = False) -> dict[str, Any]:
    """The answer's fields: ``actions`` (H, A) float32, ``future_image_predictions`` (every response field, None
    for views left out), the value under both ``VALUE_KEYS`` (``VALUE_STANDIN`` where ``resp.value`` is None, said
    in the ``wamplan`` field), with ``all_query_results`` the ``all_*`` lists of one query at search depth 1.
    ``resp.extra`` fields go along; the answer's own fields take precedence over them."""
    actions = np.ascontiguousarray(resp.actions, dtype=np.float32)  # (H, A)
    future = {name: None for name in RESPONSE_IMAGE_FIELDS}
    future.update({name: np.ascontiguousarray(img, dtype=np.uint8) for name, img in resp.future_images.items()})
    value = VALUE_STANDIN if resp.value is None else float(resp.value)
    wamplan = dict(resp.wamplan)
    if resp.value is None:
        wamplan["value_predicted"] = False
        wamplan["notes"] = [*wamplan.get("notes", []), f"the model predicts no value: {VALUE_KEYS[0]} and "
                                                       f"{VALUE_KEYS[1]} carry {VALUE_STANDIN} in its place"]
    answer = dict(resp.extra)
    answer.update({"actions": actions, "future_image_predictions": future, VALUE_KEYS[0]: value, VALUE_KEYS[1]: value})
    if all_query_results:
        answer.update(all_actions=[actions], all_future_image_predictions=[future], all_value_predictions=[value],
                      all_actions_by_depth=[[actions]], all_future_image_predictions_by_depth=[[future]],
                      all_value_predictions_by_depth=[[value]])
    if wamplan:
        answer[WAMPLAN_FIELD] = wamplan
    return answer


def decode_response(body: bytes | str) -> ActResponse:
    """Parse and check an answer (client side). Raises ErrorReply for "error", ProtocolError if malformed."""
    obj = _loads(body, "answer")
    if isinstance(obj, str) and obj != ERROR_REPLY:  # double-encoded answer
        obj = _loads(obj, "double-encoded answer")
    if isinstance(obj, str) and obj == ERROR_REPLY:
        raise ErrorReply(ERROR_REPLY)
    if isinstance(obj, list):
        raise ProtocolError("the answer is a bare action list without future_image_predictions; "
                            "the server must predict future images")
    if not isinstance(obj, Mapping):
        raise ProtocolError(f"the answer is a JSON {type(obj).__name__}, expected an object")
    if "actions" not in obj:
        raise ProtocolError(f"the answer has no 'actions' (keys: {sorted(obj)})")
    actions = _numbers(obj["actions"], "'actions'", ndim=2)  # (H, A)
    preds = obj.get("future_image_predictions")
    if not isinstance(preds, Mapping):
        raise ProtocolError("the answer has no 'future_image_predictions' dict "
                            f"(got {type(preds).__name__}); the server must predict future images")
    future = {str(k): _image(v, f"future image '{k}'") for k, v in preds.items() if v is not None}
    wamplan = obj.get(WAMPLAN_FIELD)
    wamplan = dict(wamplan) if isinstance(wamplan, Mapping) else {}
    key = next((k for k in VALUE_KEYS if obj.get(k) is not None), None)
    value = None
    if key is not None and wamplan.get("value_predicted", True):  # a stand-in value is no prediction
        value = float(_numbers([obj[key]], f"'{key}'", ndim=1).reshape(-1)[0])
    extra = {k: v for k, v in obj.items() if k not in _ANSWER_KEYS}
    return ActResponse(actions=actions, future_images=future, value=value, extra=extra, wamplan=wamplan)


# request field -> camera, and camera -> response field, for cube-insertion's cameras: the defaults of both ends.
DEFAULT_REQUEST_MAP = {"primary_image": "front", "left_wrist_image": "side", "right_wrist_image": "wrist"}
DEFAULT_RESPONSE_MAP = {"front": "future_image", "side": "future_wrist_image", "wrist": "future_wrist_image2"}


def default_maps(cameras: tuple[str, ...]) -> tuple[dict[str, str], dict[str, str]]:
    """The request and response maps for a WAM reading ``cameras`` when none are given: the defaults above for
    cube-insertion's cameras; for other cameras, camera i fills request field i of the defaults (the last camera
    fills any fields left over) and its prediction is response field i."""
    if set(cameras) == set(DEFAULT_REQUEST_MAP.values()):
        return dict(DEFAULT_REQUEST_MAP), dict(DEFAULT_RESPONSE_MAP)
    fields, futures = list(DEFAULT_REQUEST_MAP), list(DEFAULT_RESPONSE_MAP.values())
    if len(cameras) > len(fields):
        raise UserError(f"the WAM reads {len(cameras)} cameras {list(cameras)} but a request carries {len(fields)} "
                        f"images; pass a request map for the cameras to serve")
    request = {f: cameras[min(i, len(cameras) - 1)] for i, f in enumerate(fields)}
    return request, {c: futures[i] for i, c in enumerate(cameras)}


def resolve_maps(cameras: tuple[str, ...], request_map: dict[str, str] | None = None,
                 response_map: dict[str, str] | None = None) -> tuple[dict[str, str], dict[str, str]]:
    """The maps a server for ``cameras`` uses (:func:`default_maps` where none are given), checked."""
    default_request, default_response = default_maps(tuple(cameras))
    request_map = dict(request_map or default_request)
    response_map = dict(response_map or default_response)
    bad = sorted(set(request_map) - {f for fs in REQUEST_IMAGE_FIELD_SETS for f in fs})
    bad += sorted(set(response_map.values()) - set(KNOWN_RESPONSE_IMAGE_FIELDS))
    if bad:
        raise UserError(f"unknown /act field(s) {bad}; request fields are {list(REQUEST_IMAGE_FIELD_SETS)}, "
                        f"response fields {list(KNOWN_RESPONSE_IMAGE_FIELDS)}")
    unfed = [c for c in cameras if c not in request_map.values()]
    if unfed:
        raise UserError(f"camera(s) {unfed} are carried by no request field (request map: {request_map}); map them "
                        f"to a request field")
    return request_map, response_map


def field_map(request_map: dict[str, str], response_map: dict[str, str]) -> str:
    """One line: which request field feeds each camera and which answer field carries its prediction."""
    req = ", ".join(f"{name} -> {cam}" for name, cam in request_map.items())
    resp = ", ".join(f"{cam} -> {name}" for cam, name in response_map.items())
    return f"request fields: {req}; predictions: {resp}"


def fit_proprio(proprio: np.ndarray, size: int, fit: bool = False) -> tuple[np.ndarray, str | None]:
    """(P,) -> (size,) float32 with the note that says what was done (None when it already fits). A proprio of
    another length is refused (ProtocolError) unless ``fit``: then zero-padded or truncated to the model's size."""
    n = proprio.shape[0]
    if n == size:
        return proprio, None
    if not fit:
        raise ProtocolError(f"proprio has {n} entries; the model reads {size}: send {size}, or start the server "
                            f"with --fit-proprio to pad it with zeros or truncate it")
    out = np.zeros(size, dtype=np.float32)  # (size,)
    out[:min(n, size)] = proprio[:min(n, size)]
    how = f"truncated to its first {size}" if n > size else f"padded with zeros to {size}"
    return out, f"proprio of {n} entries {how}, the model's size"


def proprio_rule(size: int, fit: bool) -> str:
    """The servers' start-up line on a proprio of another length than the model's ``size``."""
    if fit:
        return f"proprio of another length than {size} padded with zeros or truncated (--fit-proprio)"
    return f"proprio of another length than {size} refused (--fit-proprio pads or truncates it)"


def clip_actions(actions: np.ndarray) -> tuple[np.ndarray, str | None]:
    """(H, A) -> (H, A) clipped to [-1, 1], with the note saying how many entries changed (None if none did)."""
    clipped = np.clip(actions, -1.0, 1.0).astype(np.float32)  # (H, A)
    changed = int(np.count_nonzero(clipped != actions))
    if not changed:
        return clipped, None
    return clipped, (f"{changed} of {actions.size} action entries were outside [-1, 1] (max |a| = "
                     f"{float(np.abs(actions).max()):.4g}) and were clipped")
