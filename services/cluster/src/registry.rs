//! The stages every neuvolex worker can run.

use neuvolex_tasks::Registry;

/// Every distributed stage of neuvolex.
pub fn standard_registry() -> Registry {
    use neuvolex_viewpoints::distributed as vp;
    Registry::new()
        .with(neuvolex_ingest::STAGE, neuvolex_ingest::IngestStage::build)
        .with(
            neuvolex_classify::pipeline::STAGE,
            neuvolex_classify::pipeline::PredictStage::build,
        )
        .with(
            neuvolex_classify::pipeline::PROBA_STAGE,
            neuvolex_classify::pipeline::ProbaStage::build,
        )
        .with(
            neuvolex_features::stage::STAGE,
            neuvolex_features::stage::ExtractStage::build,
        )
        .with(
            neuvolex_features::distributed::STAGE,
            neuvolex_features::distributed::RoundStage::build,
        )
        .with(vp::SAMPLE, vp::SampleStage::build)
        .with(vp::PASS, vp::PassStage::build)
        .with(vp::VIEWS, vp::ViewStage::build)
}
