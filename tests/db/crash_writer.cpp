// cf_db_crash_writer STORE_DIR FIRST END: performs writes FIRST..END-1 (crash_ops.hpp) through
// CaseStore and prints "ok I" on stdout after each one has committed. The crash test SIGKILLs
// it at random moments. Exit 0 when done, 2 on bad arguments, 3 on an error.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "crash_ops.hpp"

namespace {

std::int64_t find_case(cf::db::CaseStore& s, const std::string& title) {
    cf::db::CaseQuery q;
    q.text = title;
    q.sort = cf::db::CaseQuery::Sort::created_asc;
    q.limit = 10000;
    for (const auto& c : s.list_cases(q))
        if (c.title == title) return c.id;
    std::fprintf(stderr, "crash writer: case %s not found\n", title.c_str());
    std::exit(3);
}

void confirm(int i) {
    // One write(2) per line, no stdio buffer: what the parent reads was committed.
    const std::string line = "ok " + std::to_string(i) + "\n";
    if (::write(1, line.data(), line.size()) != static_cast<ssize_t>(line.size())) std::exit(3);
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 4) {
        std::fprintf(stderr, "usage: cf_db_crash_writer STORE_DIR FIRST END\n");
        return 2;
    }
    const int first = std::atoi(argv[2]), end = std::atoi(argv[3]);
    try {
        auto s = cf::db::CaseStore::open(argv[1]);
        for (int i = first; i < end; ++i) {
            const std::string title = cfcrash::case_title(i);
            switch (i % 4) {
                case 0: s->create_case(std::nullopt, title); break;
                case 1: s->set_landmarks(find_case(*s, title), cfcrash::landmark_points(i)); break;
                case 2: s->add_registration(find_case(*s, title), cfcrash::registration(i)); break;
                case 3:
                    s->import_volume_bytes(find_case(*s, title), cfcrash::payload(i), cfcrash::volume_name(i),
                                           cf::db::Modality::T1);
                    break;
            }
            confirm(i);
        }
    } catch (const std::exception& e) {
        std::fprintf(stderr, "crash writer: %s\n", e.what());
        return 3;
    }
    return 0;
}
