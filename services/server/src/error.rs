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
    /// The disk is full (507): nothing was changed; free space and retry.
    #[error("{0}")]
    Storage(String),
    /// Something failed inside (500).
    #[error("{0}")]
    Internal(String),
}

/// True when `msg` (an error's text, with its cause) says the disk or quota is full.
pub fn is_disk_full(msg: &str) -> bool {
    msg.contains("os error 28") || msg.contains("os error 122")
}

impl ApiError {
    /// An error from writing something: 507 when the disk is full, else 500.
    pub fn write_failed(msg: String) -> Self {
        if is_disk_full(&msg) {
            ApiError::Storage(msg)
        } else {
            ApiError::Internal(msg)
        }
    }
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
            ApiError::Storage(_) => StatusCode::INSUFFICIENT_STORAGE,
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
            neuvolex_bricks::BrickError::InvalidArgument(m)
            | neuvolex_bricks::BrickError::Format(
                neuvolex_formats::FormatError::InvalidArgument(m),
            ) => ApiError::BadRequest(m),
            // Another process writes the store (`neuvolex train`, `features`, ...): named.
            e @ neuvolex_bricks::BrickError::Locked { .. } => ApiError::Conflict(e.to_string()),
            other => ApiError::write_failed(other.to_string()),
        }
    }
}

impl From<neuvolex_formats::FormatError> for ApiError {
    fn from(e: neuvolex_formats::FormatError) -> Self {
        neuvolex_bricks::BrickError::from(e).into()
    }
}

impl From<neuvolex_render::RenderError> for ApiError {
    fn from(e: neuvolex_render::RenderError) -> Self {
        match e {
            neuvolex_render::RenderError::Param(_) | neuvolex_render::RenderError::Tf { .. } => {
                ApiError::BadRequest(e.to_string())
            }
            neuvolex_render::RenderError::Cancelled => ApiError::Busy(e.to_string()),
            neuvolex_render::RenderError::Bricks(b) => b.into(),
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
