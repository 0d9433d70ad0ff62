// Drafts (docs/case-store.md "Drafts"): a screen's unsaved edits kept per case, kind and owner,
// so that a restart of the browser itself loses nothing entered. Not revisions: one row per
// (case, kind, owner), replaced in place; audited when first kept and when dropped, not per
// update (an edit typed into a field is not a change of the case until it is saved).
#include "store_impl.hpp"

namespace cf::db {

using K = StoreError::Kind;
using nlohmann::json;

namespace {

void validate_draft_key(std::int64_t case_id, const std::string& kind, const std::string& owner) {
    const std::string c = "case " + std::to_string(case_id) + " draft";
    if (kind != "marks") throw StoreError(K::Invalid, c + " kind '" + kind.substr(0, 40) + "': must be marks");
    if (owner.empty() || owner.size() > 80) throw StoreError(K::Invalid, c + " owner: must be 1..80 characters");
}

}  // namespace

std::optional<DraftRecord> CaseStore::get_draft(std::int64_t case_id, const std::string& kind, const std::string& owner) {
    validate_draft_key(case_id, kind, owner);
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    I.require_case(case_id);
    auto st = I.db.prepare("SELECT user_id, body_json, saved_utc, updated_utc FROM drafts WHERE case_id = ? AND kind = ? AND owner = ?");
    st.bind(1, case_id).bind(2, kind).bind(3, owner);
    if (!st.step()) return std::nullopt;
    DraftRecord d;
    d.case_id = case_id;
    d.kind = kind;
    d.owner = owner;
    d.user_id = st.opt_i64(0);
    try {
        d.body = json::parse(st.text(1));
    } catch (const json::exception&) {
        throw StoreError(K::Corrupt, "case " + std::to_string(case_id) + " draft " + kind + " of " + owner + ": stored JSON does not parse");
    }
    d.saved_utc = parse_utc(st.text(2));
    d.updated_utc = parse_utc(st.text(3));
    return d;
}

bool CaseStore::keep_draft(std::int64_t case_id, const std::string& kind, const std::string& owner, const json& body, UtcTime saved_utc,
                           const Actor& by, const json& audit_details) {
    validate_draft_key(case_id, kind, owner);
    const std::string c = "case " + std::to_string(case_id) + " draft " + kind;
    if (!body.is_object()) throw StoreError(K::Invalid, c + ": must be a JSON object");
    if (!audit_details.is_object()) throw StoreError(K::Invalid, c + ": audit details must be a JSON object");
    const std::string text = body.dump();
    if (text.size() > kMaxDraftBytes)
        throw StoreError(K::Invalid, c + ": " + std::to_string(text.size()) + " bytes, at most " + std::to_string(kMaxDraftBytes));
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    bool existed = false;
    {
        auto st = I.db.prepare("SELECT 1 FROM drafts WHERE case_id = ? AND kind = ? AND owner = ?");
        st.bind(1, case_id).bind(2, kind).bind(3, owner);
        existed = st.step();
    }
    I.db.prepare("INSERT INTO drafts (case_id, kind, owner, user_id, body_json, saved_utc, updated_utc) VALUES (?,?,?,?,?,?,?) "
                 "ON CONFLICT (case_id, kind, owner) DO UPDATE SET user_id = excluded.user_id, body_json = excluded.body_json, "
                 "saved_utc = excluded.saved_utc, updated_utc = excluded.updated_utc")
        .bind(1, case_id).bind(2, kind).bind(3, owner).bind(4, by.user_id).bind(5, text).bind(6, format_utc(saved_utc)).bind(7, at)
        .context(c)
        .run();
    if (!existed) {
        json details = audit_details;
        details["kind"] = kind;
        I.audit_row(by, "draft.keep", case_id, details, at);
    }
    tx.commit();
    return !existed;
}

bool CaseStore::drop_draft(std::int64_t case_id, const std::string& kind, const std::string& owner, const std::string& reason, const Actor& by) {
    validate_draft_key(case_id, kind, owner);
    if (reason != "saved" && reason != "discarded")
        throw StoreError(K::Invalid, "case " + std::to_string(case_id) + " draft reason '" + reason.substr(0, 40) + "': must be saved or discarded");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    I.db.prepare("DELETE FROM drafts WHERE case_id = ? AND kind = ? AND owner = ?").bind(1, case_id).bind(2, kind).bind(3, owner).run();
    const bool had = I.db.changes() > 0;
    if (had) I.audit_row(by, "draft.drop", case_id, {{"kind", kind}, {"reason", reason}}, at);
    tx.commit();
    return had;
}

}  // namespace cf::db
