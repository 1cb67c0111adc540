//! API errors and their HTTP statuses.

use actix_web::http::StatusCode;
use actix_web::{HttpResponse, ResponseError};

/// What a request can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// The request is malformed or its values are out of range (400).
    #[error("{0}")]
    BadRequest(String),
    /// A path escapes the data root (403).
    #[error("{0}")]
    Forbidden(String),
    /// No such session, volume or resource (404).
    #[error("{0}")]
    NotFound(String),
    /// The request conflicts with the session's state (409).
    #[error("{0}")]
    Conflict(String),
    /// A mailbox is full, a limit is reached or the server is stopping: try again (503).
    #[error("{0}")]
    Busy(String),
    /// The request body is over the limit (413).
    #[error("{0}")]
    TooLarge(String),
    /// Something failed inside (500).
    #[error("{0}")]
    Internal(String),
}

impl ResponseError for ApiError {
    fn status_code(&self) -> StatusCode {
        match self {
            ApiError::BadRequest(_) => StatusCode::BAD_REQUEST,
            ApiError::Forbidden(_) => StatusCode::FORBIDDEN,
            ApiError::NotFound(_) => StatusCode::NOT_FOUND,
            ApiError::Conflict(_) => StatusCode::CONFLICT,
            ApiError::Busy(_) => StatusCode::SERVICE_UNAVAILABLE,
            ApiError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            ApiError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    fn error_response(&self) -> HttpResponse {
        HttpResponse::build(self.status_code())
            .json(serde_json::json!({ "error": self.to_string() }))
    }
}

impl From<neuvolex_bricks::BrickError> for ApiError {
    fn from(e: neuvolex_bricks::BrickError) -> Self {
        match e {
            neuvolex_bricks::BrickError::InvalidArgument(m) => ApiError::BadRequest(m),
            other => ApiError::Internal(other.to_string()),
        }
    }
}

impl From<neuvolex_render::RenderError> for ApiError {
    fn from(e: neuvolex_render::RenderError) -> Self {
        match e {
            neuvolex_render::RenderError::Param(_) | neuvolex_render::RenderError::Tf { .. } => {
                ApiError::BadRequest(e.to_string())
            }
            other => ApiError::Internal(other.to_string()),
        }
    }
}

impl From<neuvolex_classify::ClassifyError> for ApiError {
    fn from(e: neuvolex_classify::ClassifyError) -> Self {
        ApiError::BadRequest(e.to_string())
    }
}

/// Result with [`ApiError`].
pub type ApiResult<T> = Result<T, ApiError>;
