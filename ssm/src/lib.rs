//! State-space-model learning with particle filters (placeholder until the model issue).
