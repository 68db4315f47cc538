"""The config API's routers: configuration, calibration, status, web console."""

from services.config_api.models import ErrorResponse

#: Error responses every write endpoint may give (documented in OpenAPI).
WRITE_ERRORS: dict[int | str, dict] = {
    400: {"model": ErrorResponse, "description": "the body is not UTF-8 text, or Content-Length is malformed"},
    401: {"model": ErrorResponse, "description": "missing or wrong bearer token"},
    413: {"model": ErrorResponse, "description": "request body too large"},
    503: {"model": ErrorResponse, "description": "the change could not be persisted; nothing was applied"},
}
#: Error responses of read endpoints: only non-loopback clients need the token.
READ_ERRORS: dict[int | str, dict] = {401: {"model": ErrorResponse, "description": "a non-loopback client without the token"}}
#: OpenAPI of read endpoints: the token is optional (loopback clients read without it). FastAPI
#: appends this to the operation's security list, giving "bearer, or nothing".
READ_OPENAPI: dict = {"security": [{}]}
